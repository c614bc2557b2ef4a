//! The learner: actors' steps arrive over gRPC into a compact FIFO replay,
//! TD3 trains on uniformly sampled batches as a rate limiter allows, and
//! policy snapshots are published by version; checkpoints make it resumable.
//! `train` runs the learner with its actors as one command; `report` draws
//! and evaluates finished runs.

pub mod batch;
pub mod bench;
pub mod checkpoint;
pub mod config;
pub mod episodes;
pub mod exposition;
pub mod fsio;
pub mod limiter;
pub mod loopback;
pub mod metrics;
pub mod replay;
pub mod report;
pub mod serve;
pub mod service;
pub mod shared;
pub mod snapshots;
pub mod td3;
pub mod train;
pub mod training;
