//! A batch of an actor's steps as the ingest sees it, decoded at the
//! service edge, and the two answers it can get.

use super::sessions::MAX_SESSIONS;
use tweezer_gym::StepRecord;

/// One batch of an actor's steps, decoded at the service edge.
#[derive(Clone, Debug, PartialEq)]
pub struct ActorBatch {
    /// The actor's id.
    pub actor: String,
    /// The actor process's session: a random number it keeps across
    /// reconnects. Resent batches are recognised within a session; 0: the
    /// actor asks for no deduplication.
    pub session: u64,
    /// Its sequence number among the session's batches.
    pub sequence: u64,
    /// The steps, in the order they were taken.
    pub steps: Vec<StepRecord>,
}

/// The answer to a stored (or already stored) batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Ack {
    /// The batch's sequence number.
    pub sequence: u64,
    /// The newest snapshot's version (0: none).
    pub snapshot_version: u64,
    /// Whether the actor should still act uniformly at random.
    pub explore_uniformly: bool,
}

/// Why a batch was not stored.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    /// The batch is malformed; the reason names the field.
    #[error("{0}")]
    Malformed(String),
    /// The session was opened with another token.
    #[error("{0}")]
    NotYours(String),
    /// The learner tracks as many actor sessions as it may, all of them
    /// streaming.
    #[error(
        "the learner tracks {MAX_SESSIONS} actor sessions, all with open streams; try again later"
    )]
    TooManySessions,
    /// The actor went away while the batch waited for the rate limiter.
    #[error("the actor closed its stream")]
    Closed,
    /// The learner is stopping.
    #[error("the learner is shutting down")]
    ShuttingDown,
}
