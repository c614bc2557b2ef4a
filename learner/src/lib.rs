//! The learner service: actors' steps arrive over gRPC into a compact FIFO
//! replay, TD3 trains on uniformly sampled minibatches as a rate limiter
//! allows, and policy snapshots are published by version; checkpoints make
//! it resumable. The experiment runner (`tweezer-experiment`) launches it
//! with its actors and reports on finished runs.

pub mod bench;
pub mod checkpoint;
pub mod config;
pub mod divergence;
pub mod durable_write;
pub mod episodes;
pub mod fused_updates;
#[cfg(any(feature = "cuda", feature = "wgpu"))]
pub mod gpu_devices;
pub mod learner_state;
pub mod limiter;
pub mod loopback;
pub mod minibatch;
pub mod prometheus_metrics;
pub mod replay;
pub mod run_dir;
pub mod run_lock;
pub mod run_log;
pub mod serve;
pub mod service;
pub mod snapshots;
pub mod table;
pub mod td3;
pub mod tensorboard;
pub mod trainer;
