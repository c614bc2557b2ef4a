//! What a run leaves on disk: its directory and lock, checkpoints, policy
//! snapshots, the run log and TensorBoard events, each file written whole
//! or not at all.

pub mod checkpoint;
pub mod durable_write;
pub mod run_dir;
pub mod run_lock;
pub mod run_log;
pub mod snapshots;
pub mod tensorboard;
