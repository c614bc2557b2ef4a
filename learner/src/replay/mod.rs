//! The replay: compact storage of steps in a ring, which drops the oldest
//! when full (first in, first out) and samples transitions uniformly. Its
//! rate limiter and the waiting are the [`Table`](crate::ingest::table::Table)'s.
//!
//! Steps are stored, not transitions: each step record holds the observation
//! the action responded to (sphere centres and target vector — never pixels),
//! the action and the reward, and links to the record holding the next
//! observation: the same environment's next step, or a final-observation
//! record when the episode ended. Every observation is therefore stored once
//! although two transitions use it. A step becomes a sampleable transition
//! when its successor arrives.

mod storage;

pub use storage::{
    Replay, ReplayConfig, ReplayDecodeError, ReplayError, SampledTransitions, Source,
};
