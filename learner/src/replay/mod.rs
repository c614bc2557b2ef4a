//! The replay table, named after Reverb's parts: a FIFO *remover*, a
//! uniform *selector*, and compact storage.
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
