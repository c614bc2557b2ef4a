//! The replay table: FIFO order, linking, wrap-around, uniform sampling,
//! memory per transition.

use tweezer_gym::{
    Action, EnvConfig, EpisodeEnd, Observation, Outcome, RandomSteps, SplitMix64, StepRecord,
};
use tweezer_learner::replay::{Replay, ReplayConfig, ReplayError};

/// An observation that encodes `tag` in its vector (and `tag % 3` centres).
fn obs(tag: f32) -> Observation {
    Observation {
        centres: (0..(tag as usize % 3)).map(|k| [tag, k as f32]).collect(),
        vector: [tag / 1e6, 0.5],
        ..Observation::default()
    }
}

fn tag_of(vectors: &[f32], i: usize) -> f32 {
    (vectors[2 * i] * 1e6).round()
}

fn step(env: u32, episode: u64, t: u32, tag: f32, end: Option<Outcome>) -> StepRecord {
    StepRecord {
        env,
        episode,
        t,
        observation: obs(tag),
        action: Action::new(0.5, -0.5).unwrap(),
        reward: tag,
        end: end.map(|outcome| EpisodeEnd {
            outcome,
            final_observation: obs(tag + 1000.0),
        }),
    }
}

fn small(capacity: usize) -> Replay {
    Replay::new(ReplayConfig {
        capacity,
        centres_per_transition: 32,
    })
}

#[test]
fn steps_become_transitions_when_their_successor_arrives() {
    let mut replay = small(100);
    let mut rng = SplitMix64::new(1);
    assert_eq!(replay.sample(4, &mut rng), Err(ReplayError::Empty));
    replay.insert(0, &step(0, 7, 0, 1.0, None)).unwrap();
    assert!(replay.is_empty());
    replay.insert(0, &step(0, 7, 1, 2.0, None)).unwrap();
    assert_eq!(replay.len(), 1);
    let batch = replay.sample(8, &mut rng).unwrap();
    for i in 0..8 {
        assert_eq!(tag_of(&batch.vectors, i), 1.0);
        assert_eq!(tag_of(&batch.next_vectors, i), 2.0);
        assert_eq!(batch.rewards[i], 1.0);
        assert_eq!(batch.terminated[i], 0.0);
        assert_eq!(batch.centres[i], obs(1.0).centres);
        assert_eq!(batch.next_centres[i], obs(2.0).centres);
        assert_eq!(&batch.actions[2 * i..2 * i + 2], &[0.5, -0.5]);
    }
}

#[test]
fn interleaved_environments_and_actors_link_to_their_own_successors() {
    let mut replay = small(100);
    replay.insert(0, &step(0, 1, 0, 10.0, None)).unwrap();
    replay.insert(0, &step(1, 2, 0, 20.0, None)).unwrap();
    replay.insert(1, &step(0, 3, 0, 30.0, None)).unwrap();
    replay.insert(0, &step(1, 2, 1, 21.0, None)).unwrap();
    replay.insert(1, &step(0, 3, 1, 31.0, None)).unwrap();
    replay.insert(0, &step(0, 1, 1, 11.0, None)).unwrap();
    assert_eq!(replay.len(), 3);
    let batch = replay.sample(300, &mut SplitMix64::new(2)).unwrap();
    for i in 0..300 {
        let (now, next) = (tag_of(&batch.vectors, i), tag_of(&batch.next_vectors, i));
        assert_eq!(next, now + 1.0, "{now} → {next}");
    }
}

#[test]
fn episode_ends_use_the_final_observation_and_mark_termination() {
    let mut replay = small(100);
    replay
        .insert(0, &step(0, 1, 0, 5.0, Some(Outcome::Collision)))
        .unwrap();
    replay
        .insert(0, &step(1, 2, 0, 6.0, Some(Outcome::Timeout)))
        .unwrap();
    assert_eq!(replay.len(), 2);
    let batch = replay.sample(200, &mut SplitMix64::new(3)).unwrap();
    for i in 0..200 {
        let now = tag_of(&batch.vectors, i);
        assert_eq!(tag_of(&batch.next_vectors, i), now + 1000.0);
        let expected = if now == 5.0 { 1.0 } else { 0.0 };
        assert_eq!(
            batch.terminated[i], expected,
            "truncation bootstraps, termination does not"
        );
    }
    // A new episode in the same environment does not link to the old one.
    replay.insert(0, &step(0, 9, 0, 7.0, None)).unwrap();
    replay.insert(0, &step(0, 9, 1, 8.0, None)).unwrap();
    assert_eq!(replay.len(), 3);
}

#[test]
fn gaps_and_restarts_do_not_link() {
    let mut replay = small(100);
    replay.insert(0, &step(0, 1, 0, 1.0, None)).unwrap();
    replay.insert(0, &step(0, 1, 2, 3.0, None)).unwrap(); // step 1 lost
    replay.insert(0, &step(0, 4, 0, 4.0, None)).unwrap(); // restarted mid-episode
    assert!(replay.is_empty());
}

#[test]
fn fifo_removes_the_oldest_and_wraps_around() {
    let mut replay = small(50);
    for t in 0..1000u32 {
        replay.insert(0, &step(0, 1, t, t as f32, None)).unwrap();
        assert!(replay.len() <= 50);
    }
    assert_eq!(replay.len(), 50);
    assert_eq!(replay.inserted(), 999);
    let batch = replay.sample(2000, &mut SplitMix64::new(4)).unwrap();
    let tags: Vec<f32> = (0..2000).map(|i| tag_of(&batch.vectors, i)).collect();
    // Only the newest 50 complete transitions remain: steps 949..=998.
    assert!(
        tags.iter().all(|&t| (949.0..=998.0).contains(&t)),
        "{tags:?}"
    );
    assert!((949..=998).all(|t| tags.contains(&(t as f32))));
    for (centres, &tag) in batch.centres.iter().zip(&tags) {
        assert_eq!(*centres, obs(tag).centres);
    }
}

#[test]
fn every_stored_transition_is_sampled_equally_often() {
    let mut replay = small(40);
    for t in 0..41u32 {
        // Episodes of 5 steps, so final-observation records are interleaved.
        let end = (t % 5 == 4).then_some(Outcome::Timeout);
        replay
            .insert(0, &step(0, u64::from(t / 5), t % 5, t as f32, end))
            .unwrap();
    }
    let n = replay.len();
    let draws = 40_000;
    let batch = replay.sample(draws, &mut SplitMix64::new(5)).unwrap();
    let mut counts = std::collections::HashMap::new();
    for i in 0..draws {
        *counts
            .entry(tag_of(&batch.vectors, i) as u32)
            .or_insert(0usize) += 1;
    }
    assert_eq!(counts.len(), n);
    let expected = draws as f64 / n as f64;
    let chi2: f64 = counts
        .values()
        .map(|&c| (c as f64 - expected).powi(2) / expected)
        .sum();
    // 99.9th percentile of chi-square with ~40 degrees of freedom is ~73.
    assert!(chi2 < 80.0, "chi² = {chi2} over {n} transitions");
}

#[test]
fn a_full_replay_of_real_observations_stays_under_500_bytes_per_transition() {
    let capacity = 60_000;
    let mut replay = Replay::new(ReplayConfig {
        capacity,
        ..ReplayConfig::default()
    });
    let config = EnvConfig::default();
    let mut steps = RandomSteps::new(&config, 16, 11).unwrap();
    while replay.inserted() < capacity as u64 + 5_000 {
        replay.insert(0, &steps.next().unwrap()).unwrap();
    }
    assert_eq!(replay.len(), capacity);
    let per_transition = replay.bytes() as f64 / capacity as f64;
    eprintln!("replay: {per_transition:.1} bytes per transition");
    assert!(
        per_transition <= 500.0,
        "{per_transition} bytes per transition"
    );
}

#[test]
fn a_replay_survives_encoding_and_corrupt_bytes_are_refused() {
    let config = ReplayConfig {
        capacity: 500,
        ..ReplayConfig::default()
    };
    let mut replay = Replay::new(config.clone());
    for (k, record) in (RandomSteps::new(&EnvConfig::default(), 4, 9).unwrap())
        .take(800)
        .enumerate()
    {
        // Labelled, so that the guides round-trip too (NaN, none, is
        // unequal to itself).
        let guide = Some([k as f32 / 800.0, 0.5]);
        replay.insert_guided(1, &record, guide).unwrap();
    }
    let bytes = replay.encode();
    let mut back = Replay::decode(config.clone(), &bytes).unwrap();
    assert_eq!(back.len(), replay.len());
    assert_eq!(back.inserted(), replay.inserted());
    let (mut a, mut b) = (SplitMix64::new(3), SplitMix64::new(3));
    assert_eq!(
        replay.sample(64, &mut a).unwrap(),
        back.sample(64, &mut b).unwrap()
    );
    // Pending steps survive too: the next steps link to them.
    let next: Vec<_> = RandomSteps::new(&EnvConfig::default(), 4, 9)
        .unwrap()
        .skip(800)
        .take(8)
        .collect();
    for record in &next {
        replay.insert(1, record).unwrap();
        back.insert(1, record).unwrap();
    }
    assert_eq!(back.len(), replay.len());

    assert!(Replay::decode(config.clone(), &bytes[..bytes.len() - 3]).is_err());
    let mut scrambled = bytes.clone();
    scrambled[16..24].copy_from_slice(&u64::MAX.to_le_bytes());
    assert!(Replay::decode(config, &scrambled).is_err());
}

#[test]
fn steps_that_never_get_a_successor_do_not_grow_memory_beyond_the_capacity() {
    let mut replay = small(1000);
    let mut rng = SplitMix64::new(3);
    // Real transitions first, so that the sweep has live data around it.
    for t in 0..100 {
        replay.insert(0, &step(0, 1, t, 1.0, None)).unwrap();
    }
    let legit = replay.bytes();
    // Records, and the centres with their displacements, of a thousand
    // transitions at most: 1.1 MiB measured.
    let ceiling = 3 << 19;
    // A client whose steps never link: t never advances on one
    // environment, or every step comes from a new environment.
    for i in 0..400_000u32 {
        replay.insert(1, &step(7, 9, 0, 2.0, None)).unwrap();
        replay.insert(2, &step(i, 9, 0, 2.0, None)).unwrap();
        if i % 100_000 == 0 {
            assert!(replay.bytes() < ceiling, "{} bytes", replay.bytes());
        }
    }
    assert!(replay.bytes() < ceiling, "{} bytes", replay.bytes());
    assert!(replay.bytes() >= legit);
    // What links is still stored and sampled.
    for t in 0..10 {
        replay.insert(3, &step(0, 5, t, 4.0, None)).unwrap();
    }
    assert_eq!(replay.len(), 9);
    let batch = replay.sample(16, &mut rng).unwrap();
    assert!((0..16).all(|i| tag_of(&batch.vectors, i) == 4.0));
}
