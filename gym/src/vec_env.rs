//! N environments stepped in parallel with rayon, with auto-reset and
//! Gymnasium semantics: when an episode ends, its final observation is kept
//! for the transition and the slot's observation is the next episode's first.

use crate::action::Action;
use crate::config::EnvConfig;
use crate::env::{Env, Outcome, StepResult};
use crate::observation::Observation;
use crate::policy::UniformRandom;
use crate::rng::SplitMix64;
use crate::step_record::{EpisodeEnd, StepRecord};
use rayon::prelude::*;
use tweezer_config::ConfigError;

const SLOT_TAG: u64 = 0x5107_0000_0000;

/// A finished episode.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpisodeStats {
    /// The episode seed.
    pub seed: u64,
    /// Sum of rewards.
    pub episode_return: f64,
    /// Steps taken.
    pub steps: u32,
    /// How it ended.
    pub outcome: Outcome,
}

/// One environment of a [`VecEnv`] and what its last step produced.
#[derive(Clone, Debug)]
pub struct Slot {
    env: Env,
    seeds: SplitMix64,
    episode_return: f64,
    last: Option<StepResult>,
    /// The observation the last action responded to, with its episode and
    /// step index.
    observed: Observation,
    observed_at: (u64, u32),
    action: Action,
    final_observation: Observation,
    finished: Option<EpisodeStats>,
}

impl Slot {
    fn step(&mut self, action: Action) {
        self.observed.clone_from(self.env.observation());
        self.observed_at = (self.env.seed(), self.env.steps());
        self.action = action;
        let result = self
            .env
            .step(action)
            .expect("a vectorised slot resets as soon as its episode ends");
        self.episode_return += result.reward;
        self.finished = None;
        if result.done() {
            self.final_observation.clone_from(self.env.observation());
            self.finished = Some(EpisodeStats {
                seed: self.env.seed(),
                episode_return: self.episode_return,
                steps: self.env.steps(),
                outcome: result.outcome,
            });
            self.episode_return = 0.0;
            self.env.reset(self.seeds.next_u64());
        }
        self.last = Some(result);
    }

    /// The observation the next action responds to.
    pub fn observation(&self) -> &Observation {
        self.env.observation()
    }

    /// The last step's result (`None` before the first step).
    pub fn last(&self) -> Option<&StepResult> {
        self.last.as_ref()
    }

    /// The observation after the last step: the final observation of the
    /// episode if the last step ended it, else the current observation.
    pub fn next_observation(&self) -> &Observation {
        match self.finished {
            Some(_) => &self.final_observation,
            None => self.env.observation(),
        }
    }

    /// The episode the last step finished, if it did.
    pub fn finished(&self) -> Option<&EpisodeStats> {
        self.finished.as_ref()
    }

    /// The environment (positions, target, seed of the running episode).
    pub fn env(&self) -> &Env {
        &self.env
    }

    /// The last step as an actor reports it, labelled as environment `env`
    /// (`None` before the first step).
    pub fn record(&self, env: u32) -> Option<StepRecord> {
        let last = self.last?;
        let (episode, t) = self.observed_at;
        Some(StepRecord {
            env,
            episode,
            t,
            observation: self.observed.clone(),
            action: self.action,
            reward: last.reward as f32,
            end: self.finished.map(|stats| EpisodeEnd {
                outcome: stats.outcome,
                final_observation: self.final_observation.clone(),
            }),
        })
    }
}

/// Actions whose count is not the number of environments.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("got {got} actions for {expected} environments")]
pub struct ActionCountMismatch {
    /// Actions given.
    pub got: usize,
    /// Environments.
    pub expected: usize,
}

/// N environments with their own seed streams, stepped together.
#[derive(Clone, Debug)]
pub struct VecEnv {
    slots: Vec<Slot>,
}

impl VecEnv {
    /// `n` environments; slot `i` draws its episode seeds from a stream
    /// derived from `seed` and `i`, so runs are reproducible whatever the
    /// number of threads.
    pub fn new(config: &EnvConfig, n: usize, seed: u64) -> Result<Self, ConfigError> {
        let slots = (0..n)
            .map(|i| {
                let mut seeds = SplitMix64::derived(seed, SLOT_TAG + i as u64);
                let mut env = Env::new(config.clone())?;
                env.reset(seeds.next_u64());
                Ok(Slot {
                    env,
                    seeds,
                    episode_return: 0.0,
                    last: None,
                    observed: Observation::default(),
                    observed_at: (0, 0),
                    action: Action::ZERO,
                    final_observation: Observation::default(),
                    finished: None,
                })
            })
            .collect::<Result<_, ConfigError>>()?;
        Ok(Self { slots })
    }

    /// Number of environments.
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    /// Whether there are no environments.
    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// Steps every environment with its action, in parallel.
    pub fn step(&mut self, actions: &[Action]) -> Result<(), ActionCountMismatch> {
        if actions.len() != self.slots.len() {
            return Err(ActionCountMismatch {
                got: actions.len(),
                expected: self.slots.len(),
            });
        }
        self.slots
            .par_iter_mut()
            .zip(actions.par_iter())
            .for_each(|(slot, &action)| slot.step(action));
        Ok(())
    }

    /// The environments and their last results.
    pub fn slots(&self) -> &[Slot] {
        &self.slots
    }

    /// The observations the next actions respond to.
    pub fn observations(&self) -> Vec<&Observation> {
        self.slots.iter().map(Slot::observation).collect()
    }
}

/// Endless step records from `n` environments under uniformly random
/// actions, slot by slot: data for benchmarks and tests of whatever
/// consumes an actor's steps.
#[derive(Debug)]
pub struct RandomSteps {
    envs: VecEnv,
    policy: UniformRandom,
    actions: Vec<Action>,
    pending: std::vec::IntoIter<StepRecord>,
}

impl RandomSteps {
    /// `n` environments seeded from `seed`, the actions too.
    pub fn new(config: &EnvConfig, n: usize, seed: u64) -> Result<Self, ConfigError> {
        Ok(Self {
            envs: VecEnv::new(config, n, seed)?,
            policy: UniformRandom::new(seed),
            actions: vec![Action::ZERO; n],
            pending: Vec::new().into_iter(),
        })
    }
}

impl Iterator for RandomSteps {
    type Item = StepRecord;

    fn next(&mut self) -> Option<StepRecord> {
        if let Some(record) = self.pending.next() {
            return Some(record);
        }
        for action in &mut self.actions {
            *action = self.policy.sample();
        }
        self.envs.step(&self.actions).ok()?;
        let records: Vec<StepRecord> = (self.envs.slots().iter().enumerate())
            .filter_map(|(i, slot)| slot.record(i as u32))
            .collect();
        self.pending = records.into_iter();
        self.pending.next()
    }
}
