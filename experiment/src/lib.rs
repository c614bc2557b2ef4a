//! The experiment runner: `train` trains an agent in one command — a run
//! directory, `learner serve` and its actors as local processes on
//! loopback, progress, an orderly stop — and runs sweeps; `report` draws
//! the paper's figures for finished runs and evaluates their snapshots on
//! held-out seeds next to the greedy and planner baselines.

pub mod processes;
pub mod progress;
pub mod report;
pub mod sweep;
pub mod train;
pub mod train_file;
