//! Episode statistics from the steps actors send: returns summed per
//! environment as steps arrive, and a rolling window of the last 100
//! finished episodes (the paper's criterion for the best snapshot).

use crate::replay::Source;
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, VecDeque};
use tweezer_gym::{Outcome, StepRecord};

/// Episodes in the rolling window (`docs/spec.md` §4).
pub const WINDOW: usize = 100;

/// One finished episode.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Episode {
    /// Sum of its rewards.
    pub episode_return: f64,
    /// Steps taken.
    pub steps: u32,
    /// Success, collision or timeout.
    pub outcome: EpisodeOutcome,
}

/// How a finished episode ended (serialisable mirror of [`Outcome`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EpisodeOutcome {
    /// Reached the target.
    Success,
    /// Hit a free sphere.
    Collision,
    /// Hit the time limit.
    Timeout,
}

/// Rolling means over the window.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Rolling {
    /// Episodes in the window (at most [`WINDOW`]).
    pub episodes: usize,
    /// Mean return.
    pub mean_return: f64,
    /// Fraction that succeeded.
    pub success_rate: f64,
    /// Fraction that collided.
    pub collision_rate: f64,
    /// Mean length in steps.
    pub mean_steps: f64,
}

/// Running returns and the window of finished episodes.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Episodes {
    /// Return so far of each environment's running episode.
    #[serde(skip)]
    running: HashMap<(Source, u32), (u64, f64)>,
    window: VecDeque<Episode>,
    finished: u64,
}

impl Episodes {
    /// Adds one step's reward; records the episode when the step ends it.
    /// Returns the finished episode.
    pub fn step(&mut self, source: Source, step: &StepRecord) -> Option<Episode> {
        let running = self
            .running
            .entry((source, step.env))
            .or_insert((step.episode, 0.0));
        if running.0 != step.episode {
            *running = (step.episode, 0.0);
        }
        running.1 += f64::from(step.reward);
        let episode_return = running.1;
        let end = step.end.as_ref()?;
        self.running.remove(&(source, step.env));
        let episode = Episode {
            episode_return,
            steps: step.t + 1,
            outcome: match end.outcome {
                Outcome::Success => EpisodeOutcome::Success,
                Outcome::Collision => EpisodeOutcome::Collision,
                Outcome::Timeout => EpisodeOutcome::Timeout,
                // Wire validation lets no running episode end.
                Outcome::Running => return None,
            },
        };
        if self.window.len() == WINDOW {
            self.window.pop_front();
        }
        self.window.push_back(episode);
        self.finished += 1;
        Some(episode)
    }

    /// Episodes finished since the run began.
    pub fn finished(&self) -> u64 {
        self.finished
    }

    /// Means over the last [`WINDOW`] episodes.
    pub fn rolling(&self) -> Rolling {
        let n = self.window.len();
        if n == 0 {
            return Rolling::default();
        }
        let mean = |f: &dyn Fn(&Episode) -> f64| self.window.iter().map(f).sum::<f64>() / n as f64;
        let rate = |o: EpisodeOutcome| mean(&|e| f64::from(u8::from(e.outcome == o)));
        Rolling {
            episodes: n,
            mean_return: mean(&|e| e.episode_return),
            success_rate: rate(EpisodeOutcome::Success),
            collision_rate: rate(EpisodeOutcome::Collision),
            mean_steps: mean(&|e| f64::from(e.steps)),
        }
    }
}
