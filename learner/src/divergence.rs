//! Surviving a diverged update. A non-finite loss or Q puts the networks,
//! targets and optimiser states back to a copy kept after the last run of
//! finite updates; the batch that diverged is dropped and training goes on
//! with fresh samples. When rolling back does not help, training pauses
//! (an operator resumes it) instead of the learner exiting: under systemd
//! or Slurm's auto-resume an exit would only start a crash loop.

use crate::td3::{Td3, UpdateStats};
use tweezer_nets::Networks;

/// Finite updates in a row after which the networks become the copy to
/// roll back to.
pub const GOOD_RUN: u64 = 100;

/// Rollbacks without a good run in between after which training pauses.
pub const MAX_ROLLBACKS: u32 = 5;

/// What became of an update.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
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
}

/// The copy of the networks to roll back to, and how recent updates went.
pub struct DivergenceGuard<N: Networks> {
    good: Td3<N>,
    finite_in_a_row: u64,
    rollbacks: u32,
}

impl<N: Networks> DivergenceGuard<N> {
    /// Starts with `td3` as it is as the copy to roll back to.
    pub fn new(td3: &Td3<N>) -> Self {
        Self {
            good: td3.clone(),
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
                self.good = td3.clone();
                self.finite_in_a_row = 0;
                self.rollbacks = 0;
            }
            return Verdict::Finite;
        }
        let lost = td3.updates() - self.good.updates();
        *td3 = self.good.clone();
        self.finite_in_a_row = 0;
        self.rollbacks += 1;
        if self.rollbacks >= MAX_ROLLBACKS {
            self.rollbacks = 0;
            Verdict::GiveUp { lost }
        } else {
            Verdict::RolledBack { lost }
        }
    }
}
