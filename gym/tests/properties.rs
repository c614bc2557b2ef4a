//! Invariants that hold for any seed and any action sequence.

use proptest::prelude::*;
use tweezer_gym::{Action, Env, EnvConfig, Outcome, Renderer};

fn actions() -> impl Strategy<Value = Vec<(f32, f32)>> {
    prop::collection::vec((-1.0f32..=1.0, -1.0f32..=1.0), 1..200)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn any_actions_keep_the_trap_image_vector_and_spheres_consistent(seed in any::<u64>(), moves in actions()) {
        let config = EnvConfig::default();
        let renderer = Renderer::for_config(&config).unwrap();
        let mut image = vec![0u8; renderer.pixels()];
        let mut env = Env::new(config.clone()).unwrap();
        env.reset(seed);
        let start = env.trap();
        let mut path = start;
        for (x, y) in moves {
            if env.outcome() != Outcome::Running {
                break;
            }
            let action = Action::new(x, y).unwrap();
            let result = env.step(action).unwrap();
            // The trap moves exactly as commanded.
            path = [path[0] + f64::from(x) * 10.0, path[1] + f64::from(y) * 10.0];
            prop_assert_eq!(env.trap(), path);
            prop_assert!(!(result.terminated && result.truncated));
            prop_assert!(result.reward.is_finite());
            let obs = env.observation().clone();
            // The trapped sphere is always drawn at the image centre.
            renderer.render(&obs.centres, &mut image).unwrap();
            prop_assert_eq!(image[128 * 320 + 160], 1);
            prop_assert_eq!(image[127 * 320 + 159], 1);
            let [vx, vy] = obs.vector;
            prop_assert!(vx.hypot(vy) <= 1.0 + 1e-6);
            // Centres are FOV px relative to a trap at the FOV centre.
            let positions = env.free_sphere_positions();
            for c in &obs.centres {
                let world = [
                    f64::from(c[0]) - 640.0 + env.trap()[0],
                    f64::from(c[1]) - 512.0 + env.trap()[1],
                ];
                prop_assert!(positions.iter().any(|p| (p[0] - world[0]).abs() < 1e-3
                    && (p[1] - world[1]).abs() < 1e-3));
            }
            for p in &positions {
                prop_assert!((0.0..=config.world_px[0]).contains(&p[0]));
                prop_assert!((0.0..=config.world_px[1]).contains(&p[1]));
            }
        }
    }

    #[test]
    fn no_sphere_starts_near_the_trap(seed in any::<u64>()) {
        let mut env = Env::new(EnvConfig::default()).unwrap();
        env.reset(seed);
        let trap = env.trap();
        prop_assert_eq!(trap, [5120.0, 4096.0]);
        for p in env.free_sphere_positions() {
            prop_assert!((p[0] - trap[0]).hypot(p[1] - trap[1]) > 108.0);
        }
    }
}
