//! The run directory's layout, named in one place. `learner serve` writes
//! the config, metrics, snapshots and checkpoints; the experiment runner
//! adds the train file, the actors' config, logs, credentials and report.

use std::path::{Path, PathBuf};

/// A run directory: every file of a run, by what it holds.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RunDir(PathBuf);

impl RunDir {
    /// The run directory at `path`.
    pub fn new(path: impl Into<PathBuf>) -> Self {
        Self(path.into())
    }

    /// The directory itself.
    pub fn path(&self) -> &Path {
        &self.0
    }

    /// `config.toml`: the learner's effective config, written when the run
    /// starts and read again when it resumes.
    pub fn config(&self) -> PathBuf {
        self.0.join("config.toml")
    }

    /// `learner.lock`: locked by the learner serving the run, and naming
    /// its process id.
    pub fn lock(&self) -> PathBuf {
        self.0.join("learner.lock")
    }

    /// `metrics.jsonl`: the run log, one JSON object per line.
    pub fn run_log(&self) -> PathBuf {
        self.0.join("metrics.jsonl")
    }

    /// `snapshots/`: published policy snapshots.
    pub fn snapshots(&self) -> PathBuf {
        self.0.join("snapshots")
    }

    /// `snapshots/best.safetensors`: the snapshot published at the best
    /// rolling return.
    pub fn best_snapshot(&self) -> PathBuf {
        self.snapshots()
            .join(crate::persistence::snapshots::BEST_FILE)
    }

    /// `snapshots/chosen.safetensors`: a copy of the snapshot `experiment
    /// report` last evaluated for this run (the best of the kept ones on
    /// validation seeds, or `best`), under a name that stays put for the
    /// notebook and the microscope.
    pub fn chosen_snapshot(&self) -> PathBuf {
        self.snapshots().join("chosen.safetensors")
    }

    /// `checkpoints/`: the learner's checkpoints.
    pub fn checkpoints(&self) -> PathBuf {
        self.0.join("checkpoints")
    }

    /// `train.toml`: the whole train file an experiment ran.
    pub fn train_file(&self) -> PathBuf {
        self.0.join("train.toml")
    }

    /// `actor.toml`: the actors' config.
    pub fn actor_config(&self) -> PathBuf {
        self.0.join("actor.toml")
    }

    /// `logs/`: child processes' logs and the actors' reports.
    pub fn logs(&self) -> PathBuf {
        self.0.join("logs")
    }

    /// `security/`: the run's own credentials.
    pub fn security(&self) -> PathBuf {
        self.0.join("security")
    }

    /// `report/`: the figures and evaluation drawn at the end.
    pub fn report(&self) -> PathBuf {
        self.0.join("report")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_file_lies_inside_the_run_directory() {
        let run = RunDir::new("runs/quick-1");
        for path in [
            run.config(),
            run.lock(),
            run.run_log(),
            run.snapshots(),
            run.checkpoints(),
            run.train_file(),
            run.actor_config(),
            run.logs(),
            run.security(),
            run.report(),
        ] {
            assert_eq!(path.parent(), Some(run.path()), "{}", path.display());
        }
    }
}
