//! The learner service: actors' steps arrive over gRPC into a compact FIFO
//! replay, TD3 trains on uniformly sampled minibatches as a rate limiter
//! allows, and policy snapshots are published by version; checkpoints make
//! it resumable. The experiment runner (`tweezer-experiment`) launches it
//! with its actors and reports on finished runs.
//!
//! - [`ingest`]: the gRPC service, the actor sessions, the table (the
//!   replay and its rate limiter), episodes and status.
//! - [`training`]: TD3, the loop that runs it, minibatches, the divergence
//!   guard.
//! - [`persistence`]: the run directory, checkpoints, snapshots, the run
//!   log and TensorBoard.
//! - [`state`]: what the service and the training thread share.
//! - [`serve`]: the `learner serve` process, from start to final checkpoint.

pub mod bench;
pub mod config;
pub mod ingest;
pub mod persistence;
pub mod replay;
pub mod serve;
pub mod state;
pub mod training;
