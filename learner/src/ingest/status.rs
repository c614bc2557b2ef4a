//! The learner's status as GetStatus and the Prometheus metrics show it.

use super::episodes::Rolling;
use super::limiter::LimiterState;
use super::sessions::ActorSummary;

/// What training reports for status.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TrainingStatus {
    /// TD3 updates made.
    pub updates: u64,
    /// Recent mean critic loss.
    pub critic_loss: f64,
    /// Recent mean actor loss.
    pub actor_loss: f64,
    /// Recent mean Q of the sampled actions.
    pub mean_q: f64,
    /// Transitions inserted per second, recently.
    pub insert_rate: f64,
    /// Transitions sampled per second, recently.
    pub sample_rate: f64,
    /// Updates that diverged and were rolled back since this process
    /// started.
    pub diverged_updates: u64,
    /// Checkpoints that could not be written since this process started.
    pub checkpoint_failures: u64,
    /// Snapshots that could not be published since this process started.
    pub snapshot_failures: u64,
}

/// The learner's status, read at one moment.
#[derive(Clone, Debug, PartialEq)]
pub struct LearnerStatus {
    /// Transitions inserted since the run began.
    pub steps_inserted: u64,
    /// What training reports.
    pub training: TrainingStatus,
    /// Transitions in the replay.
    pub buffer_size: usize,
    /// The replay's capacity.
    pub buffer_capacity: usize,
    /// What the rate limiter is doing; `None` when the learner has none
    /// (it ingests without learning).
    pub limiter: Option<LimiterState>,
    /// Actor streams open now.
    pub connected_actors: u32,
    /// Means over the recent episodes.
    pub rolling: Rolling,
    /// Episodes finished since the run began.
    pub episodes: u64,
    /// The newest snapshot's version (0: none).
    pub latest_snapshot: u64,
    /// The best snapshot's version (0: none).
    pub best_snapshot: u64,
    /// Batches refused as malformed.
    pub malformed_batches: u64,
    /// Batches acknowledged without storing because they were stored before.
    pub duplicate_batches: u64,
    /// Whether actors should still act uniformly at random.
    pub explore_uniformly: bool,
    /// Whether an operator paused learning.
    pub paused: bool,
    /// The actor sessions tracked now, streaming ones and the most
    /// recently active first, at most [`STATUS_ACTORS`](super::sessions::STATUS_ACTORS), by id.
    pub actors: Vec<ActorSummary>,
    /// Actor sessions tracked now.
    pub known_actors: usize,
}
