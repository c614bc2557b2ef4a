//! The rate limiter: warm-up, the ratio, back-pressure, restore, and real
//! threads with 1 and 8 producers.

use std::sync::Arc;
use std::time::{Duration, Instant};
use tweezer_gym::{Action, Observation, StepRecord};
use tweezer_learner::ingest::limiter::{Limiter, LimiterConfig, LimiterState};
use tweezer_learner::ingest::table::Table;
use tweezer_learner::replay::{Replay, ReplayConfig};

fn config(ratio: f64, min_size: usize, slack: f64) -> LimiterConfig {
    LimiterConfig {
        updates_per_insert: ratio,
        min_size,
        slack,
    }
}

#[test]
fn learning_waits_for_the_minimum_then_follows_the_ratio() {
    let mut l = Limiter::new(config(1.0, 100, 10.0));
    for len in 0..100 {
        assert!(l.can_insert(1, len));
        assert!(!l.can_update(len));
        assert_eq!(l.state(len, 0), LimiterState::WarmingUp);
        l.inserted(1);
    }
    // At the minimum nothing is owed yet.
    assert!(!l.can_update(100));
    assert_eq!(l.state(100, 0), LimiterState::WaitingForData);
    l.inserted(3);
    for _ in 0..3 {
        assert!(l.can_update(103));
        l.updated();
    }
    assert!(!l.can_update(103), "the learner never runs ahead");
    // Inserts run ahead by at most the slack.
    l.inserted(10);
    assert!(!l.can_insert(1, 113));
    assert_eq!(l.state(113, 0), LimiterState::BlockingInserts);
    l.updated();
    assert!(l.can_insert(1, 113));
    assert_eq!(l.state(113, 0), LimiterState::Flowing);
    // One step would fit, but the batch that waits does not.
    assert_eq!(l.state(113, 5), LimiterState::BlockingInserts);
}

#[test]
fn fractional_ratios_and_big_batches_never_deadlock() {
    let mut l = Limiter::new(config(0.25, 10, 4.0));
    l.inserted(10);
    l.inserted(7); // owes 1.75 updates
    assert!(l.can_update(17));
    l.updated(); // 0.75 owed: no update, but inserts must go on
    assert!(!l.can_update(17));
    assert!(
        l.can_insert(1000, 17),
        "a batch larger than the slack waits for nothing"
    );
}

#[test]
fn a_restored_limiter_cannot_block_both_sides() {
    let mut l = Limiter::new(config(1.0, 100, 10.0));
    l.inserted(5_000);
    // Restored counters say 4,900 updates are owed, but the replay came back
    // empty: rebasing makes the counts agree with the replay.
    l.rebase(0);
    assert!(l.can_insert(50, 0));
    for len in 1..=150 {
        l.inserted(1);
        assert!(
            l.can_insert(1, len) || l.can_update(len),
            "deadlock at {len}"
        );
    }
    l.rebase(150);
    assert!(l.can_insert(1, 150));
}

#[test]
fn bad_settings_are_named() {
    for (c, field) in [
        (config(0.0, 1, 1.0), "limiter.updates_per_insert"),
        (config(1.0, 0, 1.0), "limiter.min_size"),
        (config(1.0, 1, 0.5), "limiter.slack"),
    ] {
        let err = c.validate().unwrap_err().to_string();
        assert!(err.contains(field), "{err}");
    }
}

/// Step `t` of one long episode.
fn step(t: u64) -> StepRecord {
    StepRecord {
        env: 0,
        episode: 0,
        t: t as u32,
        observation: Observation::default(),
        action: Action::new(0.0, 0.0).unwrap(),
        reward: 0.0,
        end: None,
    }
}

/// Producers insert batches into a table while one learner thread
/// updates; the ratio must hold throughout and everything finish.
fn run_with_producers(producers: u64) {
    let (batch, batches, min_size, slack) = (16u64, 40u64, 64usize, 32.0);
    let replay = Replay::new(ReplayConfig {
        capacity: 100_000,
        ..ReplayConfig::default()
    });
    let limiter = Limiter::new(config(1.0, min_size, slack));
    let table = Arc::new(Table::new(replay, Some(limiter)));
    let deadline = Instant::now() + Duration::from_secs(60);
    let threads: Vec<_> = (0..producers)
        .map(|p| {
            let table = table.clone();
            std::thread::spawn(move || {
                for b in 0..batches {
                    let stuck = || (Instant::now() >= deadline).then_some("producer stuck");
                    let stored = table.insert(batch, Duration::from_millis(50), stuck, |replay| {
                        for t in b * batch..(b + 1) * batch {
                            replay.insert(p as u32, &step(t)).unwrap();
                        }
                        Ok(Some(()))
                    });
                    assert_eq!(stored, Ok(Some(())));
                }
            })
        })
        .collect();
    let owed = producers * batch * batches - min_size as u64;
    let mut updates = 0;
    while updates < owed {
        assert!(
            Instant::now() < deadline,
            "learner stuck after {updates} updates"
        );
        if table.wait_to_update(Duration::from_millis(50)) {
            table.updated();
            updates += 1;
            let (counts, _) = table.limiter().unwrap();
            let credit =
                counts.inserts.saturating_sub(min_size as u64) as f64 - counts.updates as f64;
            assert!(credit >= 0.0, "the learner ran ahead: {counts:?}");
            assert!(credit <= slack, "inserts ran too far ahead: {counts:?}");
        }
    }
    for t in threads {
        t.join().unwrap();
    }
    let (counts, _) = table.limiter().unwrap();
    assert_eq!(counts.inserts, producers * batch * batches);
    assert_eq!(counts.updates, owed);
}

#[test]
fn one_producer_and_the_learner_keep_the_ratio_within_the_slack() {
    run_with_producers(1);
}

#[test]
fn eight_producers_and_the_learner_keep_the_ratio_within_the_slack() {
    run_with_producers(8);
}

/// While a batch waits for the limiter, status says inserts are blocked,
/// even when a single step would still fit within the slack.
#[test]
fn a_waiting_batch_shows_as_blocking_inserts() {
    let replay = Replay::new(ReplayConfig::default());
    let table = Arc::new(Table::new(replay, Some(Limiter::new(config(1.0, 1, 4.0)))));
    let insert = |table: &Table, steps: std::ops::Range<u64>| {
        let n = steps.end - steps.start;
        let deadline = Instant::now() + Duration::from_secs(60);
        let stuck = || (Instant::now() >= deadline).then_some("producer stuck");
        table.insert(n, Duration::from_millis(10), stuck, |replay| {
            for t in steps {
                replay.insert(0, &step(t)).unwrap();
            }
            Ok(Some(()))
        })
    };
    assert_eq!(insert(&table, 0..2), Ok(Some(())));
    assert_eq!(table.limiter().unwrap().1, LimiterState::Flowing);
    let waiting = {
        let table = table.clone();
        std::thread::spawn(move || insert(&table, 2..6))
    };
    let deadline = Instant::now() + Duration::from_secs(60);
    while table.limiter().unwrap().1 != LimiterState::BlockingInserts {
        assert!(Instant::now() < deadline, "the waiting batch never showed");
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(!waiting.is_finished());
    assert!(table.wait_to_update(Duration::from_secs(60)));
    table.updated();
    assert_eq!(waiting.join().unwrap(), Ok(Some(())));
}

/// A batch that two streams of one session deliver at once (a resend after
/// a reconnect) is stored once and counted once: the second is found to be
/// a duplicate inside the insert, after both waited for the limiter, and
/// must not charge it (which would let the update-to-insert ratio drift).
#[test]
fn a_batch_resent_on_two_streams_is_stored_and_counted_once() {
    use tweezer_gym::{EnvConfig, StepBounds};
    use tweezer_learner::ingest::batch::ActorBatch;
    use tweezer_learner::state::LearnerState;
    let batch = |sequence: u64| ActorBatch {
        actor: "actor-r".into(),
        session: 7,
        sequence,
        steps: (sequence * 8..(sequence + 1) * 8).map(step).collect(),
    };
    // After the first batch, inserts wait for updates.
    let state = Arc::new(LearnerState::new(
        Replay::new(ReplayConfig::default()),
        Some(Limiter::new(config(1.0, 1, 0.5))),
        StepBounds::for_config(&EnvConfig::default()),
    ));
    state.accept(batch(0), &mut None, None, || false).unwrap();
    let streams: Vec<_> = (0..2)
        .map(|_| {
            let state = state.clone();
            std::thread::spawn(move || state.accept(batch(1), &mut None, None, || false))
        })
        .collect();
    // Both streams wait for the limiter; the learner then updates until
    // both are answered.
    std::thread::sleep(Duration::from_millis(300));
    let deadline = Instant::now() + Duration::from_secs(60);
    while streams.iter().any(|s| !s.is_finished()) {
        assert!(Instant::now() < deadline, "a stream is stuck");
        if state.table().wait_to_update(Duration::from_millis(10)) {
            state.table().updated();
        }
    }
    for stream in streams {
        assert_eq!(stream.join().unwrap().unwrap().sequence, 1);
    }
    assert_eq!(state.steps_inserted(), 16);
    assert_eq!(state.duplicates(), 1);
    let (counts, _) = state.table().limiter().unwrap();
    assert_eq!(
        counts.inserts,
        state.steps_inserted(),
        "the limiter counted what the replay was given"
    );
}
