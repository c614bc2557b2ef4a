//! Surviving a diverged update. A non-finite loss or Q puts the networks,
//! targets and optimiser states back to a good state: a copy kept after
//! the last run of finite updates, or, where such a copy would double a
//! large learner's memory, a checkpoint on disk. The batch that diverged
//! is dropped and training goes on with fresh samples. When rolling back
//! does not help, training pauses (an operator resumes it) instead of the
//! learner exiting: under systemd or Slurm's auto-resume an exit would only
//! start a crash loop.

use crate::persistence::checkpoint::{CheckpointError, Checkpoints, read, read_header};
use crate::training::td3::{Td3, UpdateStats};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use tweezer_nets::Networks;

/// Finite updates in a row after which the networks become the copy to
/// roll back to, and after which rollbacks are counted afresh.
pub const GOOD_RUN: u64 = 100;

/// Rollbacks without a good run in between after which training pauses.
pub const MAX_ROLLBACKS: u32 = 5;

/// Largest state (networks, targets, Adam's moments) that
/// [`Rollback::Auto`] keeps a copy of in memory.
pub const AUTO_COPY_MAX_BYTES: usize = 512 << 20;

/// What a diverged update rolls back to (`learner.rollback`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Rollback {
    /// `copy` when the state takes at most [`AUTO_COPY_MAX_BYTES`] (the
    /// quick preset's), `checkpoint` otherwise (the paper preset's).
    #[default]
    Auto,
    /// A copy in memory, taken after every [`GOOD_RUN`] finite updates:
    /// at most twice that many updates are lost, at the price of the
    /// state's size in memory.
    Copy,
    /// The newest checkpoint (an older one on each rollback without a good
    /// run in between): no memory besides, at the price of the updates
    /// since it. A fresh run writes a checkpoint when training begins.
    Checkpoint,
}

/// What became of an update.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Its loss and Q were finite.
    Finite,
    /// It diverged and the networks were rolled back `lost` updates.
    RolledBack {
        /// Updates undone, the diverged one included.
        lost: u64,
    },
    /// It diverged again right after rollbacks: training should pause.
    GiveUp {
        /// Updates undone, the diverged one included.
        lost: u64,
    },
    /// It diverged and no good state could be read back: training should
    /// pause, the networks as the update left them.
    Unrestorable {
        /// Why.
        reason: String,
    },
}

/// Where the good state is kept.
enum Good<N: Networks> {
    Copy(Box<Td3<N>>),
    Checkpoints(Checkpoints),
}

/// The good state to roll back to, and how recent updates went.
pub struct DivergenceGuard<N: Networks> {
    good: Good<N>,
    finite_in_a_row: u64,
    rollbacks: u32,
}

impl<N: Networks> DivergenceGuard<N> {
    /// Keeps copies of `td3`, starting with `td3` as it is.
    pub fn with_copies(td3: &Td3<N>) -> Self {
        Self::keeping(Good::Copy(Box::new(td3.clone())))
    }

    /// Rolls back to the checkpoints in `checkpoints`: the caller makes
    /// sure one exists at or before `td3`'s updates.
    pub fn with_checkpoints(checkpoints: Checkpoints) -> Self {
        Self::keeping(Good::Checkpoints(checkpoints))
    }

    /// The guard `rollback` asks for `td3`.
    pub fn new(rollback: Rollback, td3: &Td3<N>, checkpoints: &Checkpoints) -> Self {
        if rollback.keeps_checkpoints(td3) {
            Self::with_checkpoints(checkpoints.clone())
        } else {
            Self::with_copies(td3)
        }
    }

    /// Whether the guard rolls back to checkpoints and none is there for
    /// `td3` (of its networks, at or before its updates): one should be
    /// written before training.
    pub fn needs_checkpoint(&self, td3: &Td3<N>) -> bool {
        match &self.good {
            Good::Copy(_) => false,
            Good::Checkpoints(checkpoints) => {
                !candidates(checkpoints, td3).is_ok_and(|found| !found.is_empty())
            }
        }
    }

    fn keeping(good: Good<N>) -> Self {
        Self {
            good,
            finite_in_a_row: 0,
            rollbacks: 0,
        }
    }

    /// Judges the update that produced `stats`, rolling `td3` back when it
    /// diverged.
    pub fn check(&mut self, td3: &mut Td3<N>, stats: &UpdateStats) -> Verdict {
        let finite = stats.critic_loss.is_finite()
            && stats.mean_q.is_finite()
            && stats.actor_loss.is_none_or(f64::is_finite);
        if finite {
            self.finite_in_a_row += 1;
            if self.finite_in_a_row >= GOOD_RUN {
                if let Good::Copy(good) = &mut self.good {
                    **good = td3.clone();
                }
                self.finite_in_a_row = 0;
                self.rollbacks = 0;
            }
            return Verdict::Finite;
        }
        let before = td3.updates();
        let restored = match &self.good {
            Good::Copy(good) => {
                *td3 = (**good).clone();
                Ok(())
            }
            Good::Checkpoints(checkpoints) => restore(checkpoints, td3, self.rollbacks),
        };
        self.finite_in_a_row = 0;
        if let Err(reason) = restored {
            self.rollbacks = 0;
            return Verdict::Unrestorable { reason };
        }
        let lost = before - td3.updates();
        self.rollbacks += 1;
        if self.rollbacks >= MAX_ROLLBACKS {
            self.rollbacks = 0;
            Verdict::GiveUp { lost }
        } else {
            Verdict::RolledBack { lost }
        }
    }
}

impl Rollback {
    /// Whether `td3` rolls back to checkpoints rather than to a copy.
    pub fn keeps_checkpoints<N: Networks>(self, td3: &Td3<N>) -> bool {
        match self {
            Self::Auto => td3.state_bytes() > AUTO_COPY_MAX_BYTES,
            Self::Copy => false,
            Self::Checkpoint => true,
        }
    }
}

/// Loads into `td3` the newest checkpoint at or before its updates, or the
/// `older`-th older one (the oldest there is when fewer are left), and
/// deletes the newer ones: training diverged soon after each of them.
fn restore<N: Networks>(
    checkpoints: &Checkpoints,
    td3: &mut Td3<N>,
    older: u32,
) -> Result<(), String> {
    let candidates = candidates(checkpoints, td3).map_err(|e| e.to_string())?;
    let mut why = Vec::new();
    let chosen = (older as usize).min(candidates.len().saturating_sub(1));
    for (i, path) in candidates.iter().enumerate().skip(chosen) {
        let loaded = match read(path) {
            Ok(loaded) => loaded,
            Err(e) => {
                why.push(e.to_string());
                continue;
            }
        };
        if let Err(e) = td3.load_state(|name| loaded.part(name), loaded.header.updates) {
            why.push(format!("checkpoint {}: {e}", path.display()));
            continue;
        }
        for newer in &candidates[..i] {
            match std::fs::remove_file(newer) {
                Ok(()) => tracing::warn!(
                    path = %newer.display(),
                    "checkpoint deleted: training diverged soon after it"
                ),
                Err(e) => {
                    tracing::warn!(path = %newer.display(), error = %e, "checkpoint not deleted")
                }
            }
        }
        return Ok(());
    }
    if why.is_empty() {
        why.push(format!(
            "no checkpoint of these networks at or before update {} in {}",
            td3.updates(),
            checkpoints.dir().display()
        ));
    }
    Err(why.join("; "))
}

/// The checkpoints of `td3`'s networks at or before its updates, newest
/// first, by their headers.
fn candidates<N: Networks>(
    checkpoints: &Checkpoints,
    td3: &Td3<N>,
) -> Result<Vec<PathBuf>, CheckpointError> {
    let architecture = td3.networks().architecture();
    let mut files = checkpoints.list()?;
    files.retain(|path| {
        read_header(path).is_ok_and(|header| {
            header.updates <= td3.updates() && header.architecture == architecture
        })
    });
    Ok(files)
}
