//! The replay and its rate limiter with one owner, as Reverb's `Table`:
//! inserting a batch is one transaction — wait for the limiter's credit,
//! store, count — so the inserts the limiter has counted are exactly the
//! steps the replay was given, and an update is counted as it is sampled.

use crate::ingest::limiter::{Limiter, LimiterCounts, LimiterState};
use crate::replay::Replay;
use std::ops::Deref;
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::Duration;

/// The replay and its limiter, under one lock.
#[derive(Debug)]
pub struct Table {
    inner: Mutex<Inner>,
    /// Signalled whenever an insert or an update changes what the limiter
    /// allows.
    changed: Condvar,
}

#[derive(Debug)]
struct Inner {
    replay: Replay,
    /// None: ingest alone (benchmarks, tests): inserts never wait, and no
    /// update is ever allowed.
    limiter: Option<Limiter>,
    /// The sizes of the batches waiting for the limiter, for its state.
    waiting: Vec<u64>,
}

/// The replay, read while the table is held: nothing is inserted or
/// sampled meanwhile.
pub struct ReplayGuard<'a>(MutexGuard<'a, Inner>);

impl Deref for ReplayGuard<'_> {
    type Target = Replay;

    fn deref(&self) -> &Replay {
        &self.0.replay
    }
}

impl Table {
    /// A table of `replay`, rate limited by `limiter` when given (counted
    /// from the replay's size now, which a resumed run restores).
    pub fn new(replay: Replay, limiter: Option<Limiter>) -> Self {
        let limiter = limiter.map(|mut limiter| {
            limiter.rebase(replay.len());
            limiter
        });
        Self {
            inner: Mutex::new(Inner {
                replay,
                limiter,
                waiting: Vec::new(),
            }),
            changed: Condvar::new(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Inserts a batch of `n` steps: waits until the limiter admits them,
    /// in rounds of `round` between which `give_up` may end the wait with
    /// its error; then, with the table held, `store` either stores the
    /// steps and says so (`Some`), declines (`None`: the batch turned out to
    /// be stored already) or fails. Only stored steps are counted.
    pub fn insert<T, E>(
        &self,
        n: u64,
        round: Duration,
        give_up: impl Fn() -> Option<E>,
        store: impl FnOnce(&mut Replay) -> Result<Option<T>, E>,
    ) -> Result<Option<T>, E> {
        let mut inner = self.lock();
        if !inner.admits(n) {
            inner.waiting.push(n);
            while !inner.admits(n) {
                inner = self
                    .changed
                    .wait_timeout_while(inner, round, |inner| !inner.admits(n))
                    .unwrap_or_else(|p| p.into_inner())
                    .0;
                if !inner.admits(n)
                    && let Some(e) = give_up()
                {
                    inner.stop_waiting(n);
                    return Err(e);
                }
            }
            inner.stop_waiting(n);
        }
        let stored = store(&mut inner.replay)?;
        if stored.is_some() {
            if let Some(limiter) = &mut inner.limiter {
                limiter.inserted(n);
            }
            drop(inner);
            self.changed.notify_all();
        }
        Ok(stored)
    }

    /// Waits up to `timeout` until the limiter allows an update; never
    /// without a limiter.
    pub fn wait_to_update(&self, timeout: Duration) -> bool {
        let inner = self.lock();
        if inner.limiter.is_none() {
            return false;
        }
        let (inner, waited) = self
            .changed
            .wait_timeout_while(inner, timeout, |inner| !inner.allows_update())
            .unwrap_or_else(|p| p.into_inner());
        drop(inner);
        !waited.timed_out()
    }

    /// Counts one update.
    pub fn updated(&self) {
        if let Some(limiter) = &mut self.lock().limiter {
            limiter.updated();
        }
        self.changed.notify_all();
    }

    /// The replay, held for reading (sampling, status, checkpoints).
    pub fn replay(&self) -> ReplayGuard<'_> {
        ReplayGuard(self.lock())
    }

    /// The limiter's counters and what it is doing; none without one.
    pub fn limiter(&self) -> Option<(LimiterCounts, LimiterState)> {
        let inner = self.lock();
        let len = inner.replay.len();
        let largest_waiting = inner.waiting.iter().copied().max().unwrap_or(0);
        inner
            .limiter
            .as_ref()
            .map(|l| (l.counts(), l.state(len, largest_waiting)))
    }
}

impl Inner {
    /// A batch of `n` no longer waits.
    fn stop_waiting(&mut self, n: u64) {
        if let Some(i) = self.waiting.iter().position(|&w| w == n) {
            self.waiting.swap_remove(i);
        }
    }

    fn admits(&self, n: u64) -> bool {
        self.limiter
            .as_ref()
            .is_none_or(|l| l.can_insert(n, self.replay.len()))
    }

    fn allows_update(&self) -> bool {
        self.limiter
            .as_ref()
            .is_some_and(|l| l.can_update(self.replay.len()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ingest::limiter::LimiterConfig;
    use crate::replay::ReplayConfig;

    /// Nothing stored, nothing counted: a batch declined inside the
    /// transaction leaves the limiter's count as it was.
    #[test]
    fn only_stored_steps_are_counted() {
        let limiter = Limiter::new(LimiterConfig {
            min_size: 1,
            ..LimiterConfig::default()
        });
        let table = Table::new(Replay::new(ReplayConfig::default()), Some(limiter));
        let never = || None::<()>;
        let declined = table.insert(5, Duration::from_millis(1), never, |_| Ok(None::<()>));
        assert_eq!(declined, Ok(None));
        assert_eq!(table.limiter().unwrap().0.inserts, 0);
        let stored = table.insert(5, Duration::from_millis(1), never, |_| Ok(Some(())));
        assert_eq!(stored, Ok(Some(())));
        assert_eq!(table.limiter().unwrap().0.inserts, 5);
    }
}
