//! The rate limiter, after Reverb's `SampleToInsertRatio`: learner updates
//! per inserted transition are held near a configured ratio whatever the
//! number of actors. Inserts wait when the learner falls behind (back-pressure
//! instead of unbounded queues); updates wait when the actors fall behind.
//!
//! Counts are kept relative to a *base* that a restored learner resets, so
//! restored counters can never leave both sides waiting on each other. The
//! decisions are here; the waiting is the [`Table`](crate::ingest::table::Table)'s,
//! which holds the limiter with the replay it limits.

use serde::{Deserialize, Serialize};
use tweezer_config::ConfigError;

/// The limiter's settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LimiterConfig {
    /// TD3 updates per inserted transition (the paper: 1).
    pub updates_per_insert: f64,
    /// Transitions in the replay before learning starts.
    pub min_size: usize,
    /// How far, in updates, either side may run ahead of the ratio.
    pub slack: f64,
}

impl Default for LimiterConfig {
    fn default() -> Self {
        Self {
            updates_per_insert: 1.0,
            min_size: 1_000,
            slack: 2_000.0,
        }
    }
}

impl LimiterConfig {
    /// Checks every field; the error names the first one out of range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let invalid = ConfigError::invalid;
        if !(self.updates_per_insert.is_finite() && self.updates_per_insert > 0.0) {
            return Err(invalid(
                "limiter.updates_per_insert",
                "must be finite and > 0",
            ));
        }
        if self.min_size == 0 {
            return Err(invalid("limiter.min_size", "must be at least 1"));
        }
        if !(self.slack.is_finite() && self.slack >= 1.0) {
            return Err(invalid(
                "limiter.slack",
                "must be finite and at least 1 update",
            ));
        }
        Ok(())
    }
}

/// What the limiter is doing, for status.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LimiterState {
    /// Filling the replay before learning starts.
    WarmingUp,
    /// Both sides may proceed.
    Flowing,
    /// The learner is behind: inserts wait.
    BlockingInserts,
    /// The actors are behind: updates wait.
    WaitingForData,
}

/// How status shows the limiter's state (`state`), or that learning is
/// paused (`None`).
pub fn limiter_state_name(state: Option<LimiterState>) -> &'static str {
    state.map_or("learning paused", LimiterState::as_str)
}

impl LimiterState {
    /// How status shows it.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::WarmingUp => "warming up",
            Self::Flowing => "flowing",
            Self::BlockingInserts => "blocking inserts",
            Self::WaitingForData => "waiting for data",
        }
    }
}

/// The limiter's counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LimiterCounts {
    /// Transitions inserted since the base.
    pub inserts: u64,
    /// Updates made since the base.
    pub updates: u64,
}

/// The limiter's decisions, without any waiting: unit-testable.
#[derive(Clone, Debug)]
pub struct Limiter {
    config: LimiterConfig,
    counts: LimiterCounts,
}

impl Limiter {
    /// A limiter counting from zero.
    pub fn new(config: LimiterConfig) -> Self {
        Self {
            config,
            counts: LimiterCounts::default(),
        }
    }

    /// Updates owed by the inserts so far, minus updates made.
    fn credit(&self) -> f64 {
        let learnable = self
            .counts
            .inserts
            .saturating_sub(self.config.min_size as u64);
        learnable as f64 * self.config.updates_per_insert - self.counts.updates as f64
    }

    /// Whether `n` more transitions may be inserted now: while the updates
    /// owed stay within the slack, or whenever the learner has caught up
    /// (so a batch larger than the slack cannot wait forever).
    pub fn can_insert(&self, n: u64, replay_len: usize) -> bool {
        if replay_len < self.config.min_size {
            return true;
        }
        let credit = self.credit();
        credit + n as f64 * self.config.updates_per_insert <= self.config.slack || credit < 1.0
    }

    /// Whether an update may run now: learning has started and at least one
    /// update is owed. The learner never runs ahead of the ratio.
    pub fn can_update(&self, replay_len: usize) -> bool {
        replay_len >= self.config.min_size && self.credit() >= 1.0
    }

    /// Records `n` inserted transitions.
    pub fn inserted(&mut self, n: u64) {
        self.counts.inserts += n;
    }

    /// Records one update.
    pub fn updated(&mut self) {
        self.counts.updates += 1;
    }

    /// The counters.
    pub fn counts(&self) -> LimiterCounts {
        self.counts
    }

    /// Counts from zero again with the replay as it is: what a restored
    /// learner does, so that its restored counters cannot block both sides.
    pub fn rebase(&mut self, replay_len: usize) {
        self.counts = LimiterCounts {
            inserts: replay_len as u64,
            updates: (replay_len.saturating_sub(self.config.min_size) as f64
                * self.config.updates_per_insert) as u64,
        };
    }

    /// What the limiter is doing, `largest_waiting` being the largest
    /// batch now waiting to be inserted (0: none). Inserts are blocked when
    /// that batch cannot go in, even if a single step could.
    pub fn state(&self, replay_len: usize, largest_waiting: u64) -> LimiterState {
        if replay_len < self.config.min_size {
            LimiterState::WarmingUp
        } else if !self.can_insert(largest_waiting.max(1), replay_len) {
            LimiterState::BlockingInserts
        } else if !self.can_update(replay_len) {
            LimiterState::WaitingForData
        } else {
            LimiterState::Flowing
        }
    }
}
