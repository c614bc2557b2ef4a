//! Evaluation of a policy over a list of episode seeds.

use crate::action::Action;
use crate::config::EnvConfig;
use crate::env::{Env, Outcome};
use crate::policy::Policy;
use crate::vec_env::EpisodeStats;
use rayon::prelude::*;
use serde::Serialize;
use tweezer_config::ConfigError;

/// Rates and means over evaluated episodes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct EvalSummary {
    /// Episodes evaluated.
    pub episodes: usize,
    /// Fraction that reached the target.
    pub success_rate: f64,
    /// Fraction that ended in a collision.
    pub collision_rate: f64,
    /// Fraction that hit the time limit.
    pub timeout_rate: f64,
    /// Mean episode return.
    pub mean_return: f64,
    /// Mean episode length in steps.
    pub mean_steps: f64,
    /// Mean length of the successful episodes (none without one).
    pub mean_steps_success: Option<f64>,
}

impl EvalSummary {
    /// Summarises finished episodes.
    pub fn of(episodes: &[EpisodeStats]) -> Self {
        let n = episodes.len();
        let denominator = n.max(1) as f64;
        let rate =
            |o: Outcome| episodes.iter().filter(|e| e.outcome == o).count() as f64 / denominator;
        Self {
            episodes: n,
            success_rate: rate(Outcome::Success),
            collision_rate: rate(Outcome::Collision),
            timeout_rate: rate(Outcome::Timeout),
            mean_return: episodes.iter().map(|e| e.episode_return).sum::<f64>() / denominator,
            mean_steps: episodes.iter().map(|e| f64::from(e.steps)).sum::<f64>() / denominator,
            mean_steps_success: {
                let won: Vec<f64> = episodes
                    .iter()
                    .filter(|e| e.outcome == Outcome::Success)
                    .map(|e| f64::from(e.steps))
                    .collect();
                (!won.is_empty()).then(|| won.iter().sum::<f64>() / won.len() as f64)
            },
        }
    }
}

struct Running {
    /// Position of the episode's seed in the seed list.
    index: usize,
    env: Env,
    episode_return: f64,
}

/// Runs one episode per seed, up to `batch` at a time: the policy sees the
/// running episodes' observations as one batch per step, environments step in
/// parallel, and a finished episode's place goes to the next seed. Episodes
/// are returned in seed order.
pub fn evaluate(
    config: &EnvConfig,
    policy: &mut dyn Policy,
    seeds: &[u64],
    batch: usize,
) -> Result<Vec<EpisodeStats>, ConfigError> {
    let batch = batch.max(1);
    let mut results: Vec<Option<EpisodeStats>> = vec![None; seeds.len()];
    let mut running: Vec<Running> = Vec::with_capacity(batch);
    let mut spare: Vec<Env> = Vec::new();
    let mut actions = vec![Action::ZERO; batch];
    let mut next = 0;
    loop {
        while running.len() < batch && next < seeds.len() {
            let mut env = match spare.pop() {
                Some(env) => env,
                None => Env::new(config.clone())?,
            };
            env.reset(seeds[next]);
            running.push(Running {
                index: next,
                env,
                episode_return: 0.0,
            });
            next += 1;
        }
        if running.is_empty() {
            break;
        }
        let observations: Vec<_> = running.iter().map(|r| r.env.observation()).collect();
        let actions = &mut actions[..running.len()];
        policy.act(&observations, actions);
        running
            .par_iter_mut()
            .zip(actions.par_iter())
            .for_each(|(r, &action)| {
                let step = r
                    .env
                    .step(action)
                    .expect("only running episodes are stepped");
                r.episode_return += step.reward;
            });
        let mut i = 0;
        while i < running.len() {
            if running[i].env.outcome() == Outcome::Running {
                i += 1;
                continue;
            }
            let done = running.swap_remove(i);
            results[done.index] = Some(EpisodeStats {
                seed: done.env.seed(),
                episode_return: done.episode_return,
                steps: done.env.steps(),
                outcome: done.env.outcome(),
            });
            spare.push(done.env);
        }
    }
    Ok(results
        .into_iter()
        .map(|r| r.expect("every seed's episode ran to its end"))
        .collect())
}
