//! The environment against `docs/spec.md` §2: rewards, distances, step order,
//! truncation, determinism, and the lazy simulation against an eager one.

use tweezer_gym::{
    Action, Env, EnvConfig, EpisodeOver, Greedy, Layout, Observation, Outcome, Policy,
    RewardComponent, Target, UniformRandom, VecEnv,
};

/// Free spheres that stay where they are put.
fn still_config() -> EnvConfig {
    EnvConfig {
        brownian_accel_px: 0.0,
        ..EnvConfig::default()
    }
}

const TRAP: [f64; 2] = [5000.0, 4000.0];

fn layout(target: [f64; 2], spheres: &[[f64; 2]]) -> Layout {
    Layout {
        trap: TRAP,
        target,
        spheres: spheres.iter().map(|&p| (p, [0.0, 0.0])).collect(),
    }
}

fn right() -> Action {
    Action::new(1.0, 0.0).unwrap()
}

fn step_once(config: EnvConfig, layout: &Layout, action: Action) -> (Env, tweezer_gym::StepResult) {
    let mut env = Env::new(config).unwrap();
    env.reset_to_layout(1, layout).unwrap();
    let result = env.step(action).unwrap();
    (env, result)
}

#[test]
fn carry_and_time_rewards_add_up() {
    let far = [TRAP[0] + 500.0, TRAP[1]];
    let (env, r) = step_once(still_config(), &layout(far, &[]), right());
    assert_eq!(env.trap(), [TRAP[0] + 10.0, TRAP[1]]);
    assert_eq!(r.parts.time, -1.0);
    assert_eq!(r.parts.carry, 10.0);
    assert_eq!(r.reward, 9.0);
    assert_eq!(r.outcome, Outcome::Running);
    assert!(!r.terminated && !r.truncated);

    // Diagonal: both axes move 10 px; carry is the drop in distance.
    let (_, r) = step_once(
        still_config(),
        &layout(far, &[]),
        Action::new(1.0, 1.0).unwrap(),
    );
    let expected = 500.0 - (490.0f64 * 490.0 + 100.0).sqrt();
    assert!((r.parts.carry - expected).abs() < 1e-12);

    // Moving away is negative carry.
    let (_, r) = step_once(
        still_config(),
        &layout(far, &[]),
        Action::new(-0.5, 0.0).unwrap(),
    );
    assert_eq!(r.parts.carry, -5.0);
    assert_eq!(r.reward, -6.0);
}

#[test]
fn collision_is_inclusive_at_the_sphere_diameter() {
    let far = [TRAP[0] + 500.0, TRAP[1]];
    // After the step the trap is at TRAP + 10 in x.
    for (offset, collides) in [
        (54.0, true),
        (53.0, true),
        (55.0, false),
        (54.000001, false),
    ] {
        let sphere = [TRAP[0] + 10.0 + offset, TRAP[1]];
        let (_, r) = step_once(still_config(), &layout(far, &[sphere]), right());
        assert_eq!(r.outcome == Outcome::Collision, collides, "offset {offset}");
        assert_eq!(r.terminated, collides);
        assert_eq!(r.parts.collision, if collides { -100.0 } else { 0.0 });
    }
    // Diagonal distance counts, not a box.
    let sphere = [TRAP[0] + 10.0 + 38.0, TRAP[1] + 38.0]; // 53.74 px away
    let (_, r) = step_once(still_config(), &layout(far, &[sphere]), right());
    assert_eq!(r.outcome, Outcome::Collision);
    let sphere = [TRAP[0] + 10.0 + 39.0, TRAP[1] + 39.0]; // 55.15 px away
    let (_, r) = step_once(still_config(), &layout(far, &[sphere]), right());
    assert_eq!(r.outcome, Outcome::Running);
}

#[test]
fn success_is_inclusive_at_the_sphere_radius() {
    for (offset, succeeds) in [
        (27.0, true),
        (26.0, true),
        (28.0, false),
        (27.000001, false),
    ] {
        let target = [TRAP[0] + 10.0 + offset, TRAP[1]];
        let (_, r) = step_once(still_config(), &layout(target, &[]), right());
        assert_eq!(r.outcome == Outcome::Success, succeeds, "offset {offset}");
        assert_eq!(r.terminated, succeeds);
        assert_eq!(r.parts.success, if succeeds { 1000.0 } else { 0.0 });
        if succeeds {
            assert_eq!(r.reward, -1.0 + 10.0 + 1000.0);
        }
    }
}

#[test]
fn collision_wins_over_success() {
    let target = [TRAP[0] + 20.0, TRAP[1]];
    let sphere = [TRAP[0] + 60.0, TRAP[1]];
    let (_, r) = step_once(still_config(), &layout(target, &[sphere]), right());
    assert_eq!(r.outcome, Outcome::Collision);
    assert_eq!(r.parts.success, 0.0);
    assert_eq!(r.reward, -1.0 + 10.0 - 100.0);
}

#[test]
fn free_spheres_move_before_the_stage() {
    // A sphere 66 px right of the trap moving left at 2 px/step: after its
    // move it is at +64, after the stage moves right by 10 it is 54 away.
    let far = [TRAP[0] + 500.0, TRAP[1]];
    let mut l = layout(far, &[]);
    l.spheres.push(([TRAP[0] + 66.0, TRAP[1]], [-2.0, 0.0]));
    let mut env = Env::new(still_config()).unwrap();
    env.reset_to_layout(1, &l).unwrap();
    let r = env.step(right()).unwrap();
    assert_eq!(r.outcome, Outcome::Collision);
}

#[test]
fn reward_components_switch_off() {
    let target = [TRAP[0] + 20.0, TRAP[1]];
    let sphere = [TRAP[0] + 60.0, TRAP[1]];
    let mut config = still_config();
    config.rewards.off = vec![RewardComponent::Carry, RewardComponent::Collision];
    let (_, r) = step_once(config.clone(), &layout(target, &[sphere]), right());
    assert_eq!(r.outcome, Outcome::Collision);
    assert_eq!(r.reward, -1.0);
    config.rewards.off = vec![RewardComponent::Time, RewardComponent::Success];
    let (_, r) = step_once(config, &layout([TRAP[0] + 37.0, TRAP[1]], &[]), right());
    assert_eq!(r.outcome, Outcome::Success);
    assert_eq!(r.reward, 10.0);
}

#[test]
fn episodes_truncate_at_the_time_limit() {
    let config = EnvConfig {
        time_limit: 25,
        ..still_config()
    };
    let mut env = Env::new(config).unwrap();
    env.reset_to_layout(3, &layout([TRAP[0] + 900.0, TRAP[1]], &[]))
        .unwrap();
    for t in 1..=25 {
        let r = env.step(Action::ZERO).unwrap();
        assert_eq!(r.truncated, t == 25);
        assert!(!r.terminated);
    }
    assert_eq!(env.outcome(), Outcome::Timeout);
    assert_eq!(env.step(Action::ZERO), Err(EpisodeOver(Outcome::Timeout)));
}

#[test]
fn observation_vector_points_at_the_target_and_is_clipped() {
    let mut env = Env::new(still_config()).unwrap();
    env.reset_to_layout(1, &layout([TRAP[0], TRAP[1] - 1000.0], &[]))
        .unwrap();
    assert_eq!(env.observation().vector, [0.0, -1.0]);
    env.step(Action::new(0.0, -1.0).unwrap()).unwrap();
    assert!((env.observation().vector[1] + 0.99).abs() < 1e-6);
    // Moving away: the vector would exceed 1 and is clipped.
    for _ in 0..3 {
        env.step(Action::new(1.0, 1.0).unwrap()).unwrap();
    }
    let [x, y] = env.observation().vector;
    assert!((x.hypot(y) - 1.0).abs() < 1e-6);
    assert!(x < 0.0 && y < 0.0);
}

#[test]
fn the_observation_lists_spheres_overlapping_the_fov_in_fov_px() {
    // FOV: 1280 x 1024 around the trap; its left edge is at TRAP.x - 640.
    let spheres = [
        [TRAP[0] - 640.0 - 27.0, TRAP[1]], // touches the left edge: listed
        [TRAP[0] - 640.0 - 27.5, TRAP[1]], // just outside: not listed
        [TRAP[0] + 640.0 + 19.0, TRAP[1] + 512.0 + 19.0], // corner, 26.9 px away: listed
        [TRAP[0] + 640.0 + 20.0, TRAP[1] + 512.0 + 20.0], // corner, 28.3 px away: not listed
        [TRAP[0] + 100.0, TRAP[1] - 200.0], // inside
    ];
    let mut env = Env::new(still_config()).unwrap();
    let obs = env
        .reset_to_layout(1, &layout([TRAP[0] + 900.0, TRAP[1]], &spheres))
        .unwrap();
    let mut centres = obs.centres.clone();
    centres.sort_by(|a, b| a.partial_cmp(b).unwrap());
    assert_eq!(
        centres,
        vec![[-27.0, 512.0], [740.0, 312.0], [1299.0, 1043.0]]
    );
}

/// Runs one episode with a policy, returning per-step observations and the
/// trap's path.
fn run(env: &mut Env, policy: &mut dyn Policy) -> (Vec<Observation>, Vec<[f64; 2]>, Outcome) {
    let mut observations = vec![env.observation().clone()];
    let mut path = vec![env.trap()];
    let mut action = [Action::ZERO];
    while env.outcome() == Outcome::Running {
        policy.act(&[env.observation()], &mut action);
        env.step(action[0]).unwrap();
        observations.push(env.observation().clone());
        path.push(env.trap());
    }
    (observations, path, env.outcome())
}

#[test]
fn same_seed_same_episode() {
    for seed in [0, 1, 99, u64::MAX] {
        let mut a = Env::new(EnvConfig::default()).unwrap();
        let mut b = Env::new(EnvConfig::default()).unwrap();
        a.reset(seed);
        b.reset(seed);
        assert_eq!(
            run(&mut a, &mut UniformRandom::new(seed)),
            run(&mut b, &mut UniformRandom::new(seed))
        );
        assert_eq!(a.free_sphere_positions(), b.free_sphere_positions());
    }
    let mut a = Env::new(EnvConfig::default()).unwrap();
    let mut b = Env::new(EnvConfig::default()).unwrap();
    a.reset(1);
    b.reset(2);
    assert_ne!(a.free_sphere_positions(), b.free_sphere_positions());
}

#[test]
fn sphere_count_is_in_the_configured_range() {
    let config = EnvConfig::default();
    let mut env = Env::new(config.clone()).unwrap();
    let counts: Vec<usize> = (0..200)
        .map(|seed| {
            env.reset(seed);
            env.free_sphere_count()
        })
        .collect();
    assert!(counts.iter().all(|&n| (500..=1000).contains(&n)));
    assert!(counts.iter().any(|&n| n < 600) && counts.iter().any(|&n| n > 900));
}

#[test]
fn targets_are_at_the_configured_distance() {
    let mut env = Env::new(EnvConfig::default()).unwrap();
    for seed in 0..50 {
        env.reset(seed);
        assert!((env.initial_distance() - 1000.0).abs() < 1e-9);
        let [x, y] = env.observation().vector;
        assert!((x.hypot(y) - 1.0).abs() < 1e-6);
    }
}

/// The paper's Fig. 6: one seed, twelve targets, identical free-sphere motion.
#[test]
fn free_sphere_motion_does_not_depend_on_the_target() {
    // No collisions, so that every episode runs to its target (~100 steps).
    let config = EnvConfig {
        collision_radius_px: 0.0,
        ..EnvConfig::default()
    };
    let steps = 120;
    let mut reference: Option<Vec<Vec<[f64; 2]>>> = None;
    for k in 0..12 {
        let mut env = Env::new(config.clone()).unwrap();
        env.reset_with_target(
            7,
            Target::Angle(f64::from(k) * std::f64::consts::TAU / 12.0),
        )
        .unwrap();
        let mut policy = Greedy;
        let mut action = [Action::ZERO];
        let mut positions = vec![env.free_sphere_positions()];
        for _ in 0..steps {
            if env.outcome() != Outcome::Running {
                break;
            }
            policy.act(&[env.observation()], &mut action);
            env.step(action[0]).unwrap();
            positions.push(env.free_sphere_positions());
        }
        match &reference {
            None => reference = Some(positions),
            Some(r) => {
                let n = r.len().min(positions.len());
                assert!(n > 80, "episodes too short to compare: {n} steps");
                assert_eq!(r[..n], positions[..n], "target {k}");
            }
        }
    }
}

/// Brute force: the observation an eager simulation gives, from every free
/// sphere's position.
fn eager_centres(config: &EnvConfig, trap: [f64; 2], spheres: &[[f64; 2]]) -> Vec<[f32; 2]> {
    let (fw, fh) = (f64::from(config.fov_px[0]), f64::from(config.fov_px[1]));
    let r = config.sphere_radius_px();
    let mut out: Vec<[f32; 2]> = spheres
        .iter()
        .map(|p| (p[0] - trap[0] + fw / 2.0, p[1] - trap[1] + fh / 2.0))
        .filter(|&(x, y)| {
            let dx = (-x).max(x - fw).max(0.0);
            let dy = (-y).max(y - fh).max(0.0);
            dx * dx + dy * dy <= r * r
        })
        .map(|(x, y)| [x as f32, y as f32])
        .collect();
    out.sort_by(|a, b| a.partial_cmp(b).unwrap());
    out
}

/// The lazy simulation must see exactly what simulating every sphere every
/// step sees: the same observation, the same collisions.
#[test]
fn lazy_simulation_equals_eager_simulation() {
    let dense = EnvConfig {
        min_free_spheres: 3000,
        max_free_spheres: 4000,
        ..EnvConfig::default()
    };
    for config in [EnvConfig::default(), dense] {
        let mut outcomes = std::collections::HashSet::new();
        for seed in 0..24u64 {
            let mut lazy = Env::new(config.clone()).unwrap();
            let mut eager = Env::new(config.clone()).unwrap();
            lazy.reset(seed);
            eager.reset(seed);
            let mut random = UniformRandom::new(seed);
            let mut action = [Action::ZERO];
            loop {
                let positions = eager.free_sphere_positions();
                let mut seen = lazy.observation().centres.clone();
                seen.sort_by(|a, b| a.partial_cmp(b).unwrap());
                assert_eq!(
                    seen,
                    eager_centres(&config, lazy.trap(), &positions),
                    "seed {seed} step {}",
                    lazy.steps()
                );
                let collided = positions
                    .iter()
                    .any(|p| (p[0] - lazy.trap()[0]).hypot(p[1] - lazy.trap()[1]) <= 54.0);
                assert_eq!(collided, lazy.outcome() == Outcome::Collision);
                if lazy.outcome() != Outcome::Running {
                    break;
                }
                // Half the episodes greedy, half random: long and short paths.
                if seed % 2 == 0 {
                    Greedy.act(&[lazy.observation()], &mut action);
                } else {
                    random.act(&[lazy.observation()], &mut action);
                }
                let a = lazy.step(action[0]).unwrap();
                let b = eager.step(action[0]).unwrap();
                assert_eq!(a, b);
            }
            outcomes.insert(lazy.outcome());
        }
        assert!(outcomes.contains(&Outcome::Collision), "{outcomes:?}");
    }
}

#[test]
fn vectorised_stepping_is_deterministic_across_thread_counts() {
    let config = EnvConfig::default();
    let run_with = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut envs = VecEnv::new(&config, 8, 42).unwrap();
            let mut random = UniformRandom::new(5);
            let mut actions = vec![Action::ZERO; 8];
            let mut log = Vec::new();
            for _ in 0..400 {
                random.act(&envs.observations(), &mut actions);
                envs.step(&actions).unwrap();
                for slot in envs.slots() {
                    log.push((
                        slot.last().copied(),
                        slot.next_observation().clone(),
                        slot.finished().copied(),
                        slot.observation().clone(),
                    ));
                }
            }
            log
        })
    };
    let one = run_with(1);
    assert_eq!(one, run_with(2));
    assert!(
        one.iter().any(|(_, _, finished, _)| finished.is_some()),
        "no episode ended"
    );
}

#[test]
fn vectorised_envs_auto_reset_and_keep_the_final_observation() {
    let config = EnvConfig {
        time_limit: 30,
        ..EnvConfig::default()
    };
    let mut envs = VecEnv::new(&config, 3, 9).unwrap();
    let first_seeds: Vec<u64> = envs.slots().iter().map(|s| s.env().seed()).collect();
    assert_eq!(envs.step(&[Action::ZERO; 2]).unwrap_err().expected, 3);
    let mut ended = 0;
    for t in 1..=30 {
        envs.step(&[Action::ZERO; 3]).unwrap();
        for (i, slot) in envs.slots().iter().enumerate() {
            if let Some(done) = slot.finished() {
                ended += 1;
                assert_eq!(done.seed, first_seeds[i]);
                // A fresh episode is running with a new seed.
                assert_ne!(slot.env().seed(), first_seeds[i]);
                assert_eq!(slot.env().steps(), 0);
                assert_ne!(slot.next_observation(), slot.observation());
                let last = slot.last().unwrap();
                assert!(last.done());
                assert_eq!(last.truncated, t == 30 && done.outcome == Outcome::Timeout);
            } else {
                assert_eq!(slot.next_observation(), slot.observation());
            }
        }
    }
    assert_eq!(ended, 3, "every episode ends by the time limit");
}

#[test]
fn invalid_configs_are_refused_up_front() {
    let bad = EnvConfig {
        time_limit: 0,
        ..EnvConfig::default()
    };
    assert!(Env::new(bad.clone()).is_err());
    assert!(VecEnv::new(&bad, 2, 0).is_err());
    let err = tweezer_gym::evaluate(&bad, &mut Greedy, &[1, 2], 4).unwrap_err();
    assert!(err.to_string().contains("time_limit"), "{err}");
}

#[test]
fn impossible_episodes_are_refused() {
    let mut env = Env::new(still_config()).unwrap();
    assert!(env.reset_with_target(1, Target::Angle(f64::NAN)).is_err());
    let outside = layout([TRAP[0] + 900.0, TRAP[1]], &[[-5.0, 100.0]]);
    let err = env.reset_to_layout(1, &outside).unwrap_err();
    assert!(err.to_string().contains("sphere 0"), "{err}");
    let mut fast = layout([TRAP[0] + 900.0, TRAP[1]], &[]);
    fast.spheres.push(([100.0, 100.0], [3.0, 0.0]));
    assert!(env.reset_to_layout(1, &fast).is_err());
    let lost = layout([f64::INFINITY, 0.0], &[]);
    assert!(env.reset_to_layout(1, &lost).is_err());
}

#[test]
fn slot_records_chain_into_transitions() {
    let config = EnvConfig {
        time_limit: 40,
        ..EnvConfig::default()
    };
    let mut envs = VecEnv::new(&config, 2, 5).unwrap();
    assert!(envs.slots()[0].record(0).is_none());
    let mut policy = UniformRandom::new(8);
    let mut actions = [Action::ZERO; 2];
    let mut previous: Vec<Option<tweezer_gym::StepRecord>> = vec![None, None];
    let mut ends = 0;
    for _ in 0..100 {
        let before: Vec<Observation> = envs
            .slots()
            .iter()
            .map(|s| s.observation().clone())
            .collect();
        policy.act(&envs.observations(), &mut actions);
        envs.step(&actions).unwrap();
        for (i, slot) in envs.slots().iter().enumerate() {
            let record = slot.record(i as u32).unwrap();
            assert_eq!(record.observation, before[i]);
            assert_eq!(record.action, actions[i]);
            assert_eq!(
                f64::from(record.reward),
                slot.last().unwrap().reward as f32 as f64
            );
            if let Some(p) = &previous[i]
                && p.end.is_none()
            {
                assert_eq!((record.episode, record.t), (p.episode, p.t + 1));
            } else {
                assert_eq!(record.t, 0);
            }
            if let Some(end) = &record.end {
                ends += 1;
                assert_eq!(&end.final_observation, slot.next_observation());
                assert_eq!(record.terminated(), slot.last().unwrap().terminated);
            }
            previous[i] = Some(record);
        }
    }
    assert!(ends >= 4, "{ends} episodes ended");
}

#[test]
fn driving_the_trap_from_outside_replays_the_stepped_episode() {
    let config = EnvConfig::default();
    let mut stepped = Env::new(config.clone()).unwrap();
    let mut driven = Env::new(config).unwrap();
    stepped.reset(9);
    driven.reset(9);
    let mut policy = UniformRandom::new(3);
    for _ in 0..200 {
        let action = policy.sample();
        if stepped.step(action).unwrap().done() {
            break;
        }
        let observation = driven.drive_to(stepped.trap()).unwrap();
        assert_eq!(observation, stepped.observation());
    }
    // A non-finite position leaves the trap in place; time still passes.
    let trap = driven.trap();
    driven.drive_to([f64::NAN, 0.0]).unwrap();
    assert_eq!(driven.trap(), trap);
    let mut short = Env::new(EnvConfig {
        time_limit: 2,
        ..EnvConfig::default()
    })
    .unwrap();
    short.reset(1);
    short.drive_to([0.0, 0.0]).unwrap();
    short.drive_to([0.0, 0.0]).unwrap();
    assert_eq!(
        short.drive_to([0.0, 0.0]).unwrap_err(),
        EpisodeOver(Outcome::Timeout)
    );
}
