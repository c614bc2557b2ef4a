//! Sphere motion in the observation and the planner that uses it: the
//! matched displacements against the environment's true motion, and a
//! planner that reads nothing but the observation.

use tweezer_gym::{
    Action, Env, EnvConfig, Greedy, Layout, Observation, Outcome, Planner, Policy, UniformRandom,
    evaluate,
};

/// Every free sphere's world position mapped into the field of view, with
/// its index: where each listed centre comes from.
fn in_view(env: &mut Env) -> Vec<(usize, [f64; 2])> {
    let config = env.config().clone();
    let trap = env.trap();
    let origin = [0, 1].map(|a| trap[a] - 0.5 * f64::from(config.fov_px[a]));
    let r = config.sphere_radius_px();
    env.free_sphere_positions()
        .into_iter()
        .enumerate()
        .map(|(k, p)| (k, [p[0] - origin[0], p[1] - origin[1]]))
        .filter(|(_, [x, y])| {
            let dx = (-x).max(x - f64::from(config.fov_px[0])).max(0.0);
            let dy = (-y).max(y - f64::from(config.fov_px[1])).max(0.0);
            dx * dx + dy * dy <= r * r
        })
        .collect()
}

/// The sphere whose centre is listed at `centre`.
fn sphere_at(spheres: &[(usize, [f64; 2])], centre: [f32; 2]) -> usize {
    let (k, _) = spheres
        .iter()
        .min_by(|a, b| {
            let d = |p: [f64; 2]| (p[0] - f64::from(centre[0])).hypot(p[1] - f64::from(centre[1]));
            d(a.1).total_cmp(&d(b.1))
        })
        .expect("a listed centre has a sphere");
    *k
}

#[test]
fn matched_displacements_are_the_true_motion_and_newcomers_are_flagged() {
    let config = EnvConfig::default();
    let (mut matched, mut new) = (0, 0);
    for seed in 0..40 {
        let mut env = Env::new(config.clone()).unwrap();
        env.reset(seed);
        assert!(
            env.observation().displacements.iter().all(Option::is_none),
            "at the start every sphere is new"
        );
        let mut before = env.free_sphere_positions();
        let mut seen: Vec<usize> = in_view(&mut env).into_iter().map(|(k, _)| k).collect();
        let mut random = UniformRandom::new(seed);
        let mut action = [Action::ZERO];
        while env.outcome() == Outcome::Running {
            // Half the episodes greedy, half random: every stage motion.
            if seed % 2 == 0 {
                Greedy.act(&[env.observation()], &mut action);
            } else {
                random.act(&[env.observation()], &mut action);
            }
            env.step(action[0]).unwrap();
            let after = env.free_sphere_positions();
            let spheres = in_view(&mut env);
            let obs = env.observation().clone();
            assert_eq!(obs.displacements.len(), obs.centres.len());
            for (i, &centre) in obs.centres.iter().enumerate() {
                let k = sphere_at(&spheres, centre);
                match obs.displacements[i] {
                    Some(d) => {
                        let truth = [0, 1].map(|a| after[k][a] - before[k][a]);
                        for a in 0..2 {
                            assert!(
                                (f64::from(d[a]) - truth[a]).abs() < 1e-3,
                                "seed {seed} step {}: sphere {k} moved {truth:?}, matched {d:?}",
                                env.steps()
                            );
                        }
                        matched += 1;
                    }
                    None => {
                        assert!(
                            !seen.contains(&k),
                            "seed {seed} step {}: sphere {k} was in view and is called new",
                            env.steps()
                        );
                        new += 1;
                    }
                }
            }
            before = after;
            seen = spheres.into_iter().map(|(k, _)| k).collect();
        }
    }
    assert!(
        matched > 10_000 && new > 100,
        "{matched} matched, {new} new"
    );
}

/// A layout whose spheres in view are `visible`, and whose world, trap,
/// target and spheres out of view are shifted by `shift` and joined by
/// `hidden` ones.
fn layout(shift: f64, visible: &[[f64; 2]], hidden: &[([f64; 2], [f64; 2])]) -> Layout {
    let trap = [4000.0 + shift, 3000.0 + shift];
    Layout {
        trap,
        target: [trap[0] + 600.0, trap[1] - 800.0],
        spheres: visible
            .iter()
            .map(|&[x, y]| ([trap[0] + x, trap[1] + y], [1.5, -0.5]))
            .chain(hidden.iter().copied())
            .collect(),
    }
}

#[test]
fn the_planner_acts_on_the_observation_alone_and_deterministically() {
    let config = EnvConfig::default();
    let visible = [[120.0, -200.0], [60.0, -90.0], [-300.0, 250.0]];
    let scenes = [
        layout(0.0, &visible, &[]),
        layout(
            700.0,
            &visible,
            &[
                ([100.0, 100.0], [2.0, 2.0]),
                ([9000.0, 7000.0], [-1.0, 0.0]),
            ],
        ),
    ];
    let mut observations: Vec<Observation> = Vec::new();
    for scene in &scenes {
        let mut env = Env::new(config.clone()).unwrap();
        env.reset_to_layout(7, scene).unwrap();
        env.step(Action::new(0.5, -0.5).unwrap()).unwrap();
        observations.push(env.observation().clone());
    }
    assert_eq!(
        observations[0], observations[1],
        "the scenes differ only out of view"
    );
    assert!(observations[0].displacements.iter().all(Option::is_some));
    let mut planner = Planner::for_config(&config);
    let first = planner.action(&observations[0]);
    assert_eq!(planner.action(&observations[1]), first);
    // No memory between calls, and a batch acts as its members alone.
    let other = Observation {
        centres: vec![[700.0, 400.0]],
        displacements: vec![None],
        vector: [-0.3, 0.2],
    };
    let mut batch = [Action::ZERO; 3];
    planner.act(&[&observations[0], &other, &observations[1]], &mut batch);
    assert_eq!(batch[0], first);
    assert_eq!(batch[2], first);
    assert_eq!(batch[1], Planner::for_config(&config).action(&other));
}

#[test]
fn the_planner_dodges_where_greedy_collides() {
    let config = EnvConfig::default();
    let seeds: Vec<u64> = (0..24).collect();
    let greedy = evaluate(&config, &mut Greedy, &seeds, 8).unwrap();
    let planner = evaluate(&config, &mut Planner::for_config(&config), &seeds, 8).unwrap();
    let collided: Vec<u64> = greedy
        .iter()
        .filter(|e| e.outcome == Outcome::Collision)
        .map(|e| e.seed)
        .collect();
    assert!(collided.len() >= 8, "greedy collides on {collided:?}");
    for episode in &planner {
        assert_eq!(
            episode.outcome,
            Outcome::Success,
            "the planner on seed {}",
            episode.seed
        );
    }
}
