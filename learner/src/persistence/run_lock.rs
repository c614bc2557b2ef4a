//! One learner per run directory. Two learners serving one directory
//! overwrite each other's snapshots and checkpoints, so `learner serve`
//! holds an advisory lock on `learner.lock` for as long as it runs (the
//! operating system drops it when the process ends, however it ends), and
//! a second one is refused, naming the holder's process id.

use crate::persistence::run_dir::RunDir;
use anyhow::{Context, bail};
use std::fs::{File, OpenOptions, TryLockError};
use std::io::Write;

/// The lock on a run directory, held until dropped.
#[derive(Debug)]
pub struct RunLock {
    _file: File,
}

impl RunLock {
    /// Locks `run_dir` (which must exist) for this process, or says which
    /// process holds it.
    pub fn acquire(run_dir: &RunDir) -> anyhow::Result<Self> {
        let path = run_dir.lock();
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .with_context(|| format!("cannot open {}", path.display()))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                let holder = std::fs::read_to_string(&path).unwrap_or_default();
                let holder = holder.trim();
                let holder = if holder.is_empty() { "unknown" } else { holder };
                bail!(
                    "{} is in use by another learner (process {holder}): stop it first, or serve this one from another run directory",
                    run_dir.path().display()
                );
            }
            Err(TryLockError::Error(e)) => {
                return Err(e).with_context(|| format!("cannot lock {}", path.display()));
            }
        }
        file.set_len(0)
            .and_then(|()| writeln!(file, "{}", std::process::id()))
            .with_context(|| format!("cannot write {}", path.display()))?;
        Ok(Self { _file: file })
    }
}
