//! One environment step as an actor reports it to the learner.

use crate::action::Action;
use crate::env::Outcome;
use crate::observation::Observation;

/// One step of one environment. The transition of step `t` is
/// (observation, action, reward, next observation), where the next
/// observation is that of step `t + 1` of the same environment and episode,
/// or the final observation carried by `end`.
#[derive(Clone, Debug, PartialEq)]
pub struct StepRecord {
    /// Index of the environment within its actor.
    pub env: u32,
    /// The episode's seed.
    pub episode: u64,
    /// Step index within the episode, from 0.
    pub t: u32,
    /// The observation the action responded to.
    pub observation: Observation,
    /// The action taken.
    pub action: Action,
    /// The step's reward.
    pub reward: f32,
    /// Set when this step ended the episode.
    pub end: Option<EpisodeEnd>,
}

/// How a step ended its episode.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeEnd {
    /// Success or collision (terminated), or timeout (truncated).
    pub outcome: Outcome,
    /// The observation after the step.
    pub final_observation: Observation,
}

impl StepRecord {
    /// The step ended the episode in success or collision.
    pub fn terminated(&self) -> bool {
        matches!(&self.end, Some(e) if matches!(e.outcome, Outcome::Success | Outcome::Collision))
    }

    /// The step hit the time limit.
    pub fn truncated(&self) -> bool {
        matches!(&self.end, Some(e) if e.outcome == Outcome::Timeout)
    }
}
