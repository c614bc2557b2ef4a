//! Mirrored steps are steps the environment takes: the same layout,
//! mirrored about the trap, driven by the mirrored action, gives the
//! mirrored observations and the same reward.

use tweezer_gym::{Action, Env, EnvConfig, Layout, Observation, SplitMix64};
use tweezer_learner::replay::SampledTransitions;
use tweezer_learner::training::mirror::mirror;

const TRAP: [f64; 2] = [5120.0, 4096.0];

/// A field of spheres around the trap (none touching it), moving at
/// constant velocity: with Brownian kicks the two worlds would draw
/// different ones.
fn layout(rng: &mut SplitMix64) -> Layout {
    let mut spheres = Vec::new();
    while spheres.len() < 14 {
        let offset = [rng.uniform(-760.0, 760.0), rng.uniform(-620.0, 620.0)];
        if offset[0].hypot(offset[1]) > 150.0 {
            let velocity = [rng.uniform(-2.0, 2.0), rng.uniform(-2.0, 2.0)];
            spheres.push(([TRAP[0] + offset[0], TRAP[1] + offset[1]], velocity));
        }
    }
    Layout {
        trap: TRAP,
        target: [TRAP[0] + 700.0, TRAP[1] - 350.0],
        spheres,
    }
}

fn mirrored(layout: &Layout, flip: [bool; 2]) -> Layout {
    let about = |p: [f64; 2], centre: [f64; 2]| {
        [0, 1].map(|a| {
            if flip[a] {
                2.0 * centre[a] - p[a]
            } else {
                p[a]
            }
        })
    };
    Layout {
        trap: TRAP,
        target: about(layout.target, TRAP),
        spheres: (layout.spheres.iter())
            .map(|&(p, v)| (about(p, TRAP), about(v, [0.0; 2])))
            .collect(),
    }
}

/// The second step of `layout` under `action` (so that displacements are
/// known), as a sampled batch of one.
fn second_step(layout: &Layout, action: [f32; 2]) -> SampledTransitions {
    let mut env = Env::new(EnvConfig {
        brownian_accel_px: 0.0,
        ..EnvConfig::default()
    })
    .unwrap();
    env.reset_to_layout(1, layout).unwrap();
    let act = Action::new(action[0], action[1]).unwrap();
    env.step(act).unwrap();
    let before: Observation = env.observation().clone();
    let step = env.step(act).unwrap();
    let after = env.observation();
    SampledTransitions {
        centres: vec![before.centres.clone()],
        displacements: vec![before.displacements.clone()],
        vectors: before.vector.to_vec(),
        actions: action.to_vec(),
        rewards: vec![step.reward as f32],
        terminated: vec![f32::from(u8::from(step.terminated))],
        steps: vec![1.0],
        next_centres: vec![after.centres.clone()],
        next_displacements: vec![after.displacements.clone()],
        next_vectors: after.vector.to_vec(),
        guides: vec![f32::NAN, f32::NAN],
    }
}

fn assert_close(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: {a:?} against {b:?}");
    for (x, y) in a.iter().zip(b) {
        assert!((x - y).abs() < 1e-3, "{what}: {a:?} against {b:?}");
    }
}

fn flat(rows: &[Vec<[f32; 2]>]) -> Vec<f32> {
    rows.iter().flatten().flatten().copied().collect()
}

fn flat_moves(rows: &[Vec<Option<[f32; 2]>>]) -> Vec<f32> {
    (rows.iter().flatten())
        .flat_map(|d| d.map_or([f32::MAX; 2], |d| d))
        .collect()
}

#[test]
fn a_mirrored_step_is_the_step_the_environment_takes_in_the_mirrored_world() {
    let mut rng = SplitMix64::new(17);
    let fov = EnvConfig::default().fov_px;
    for _ in 0..4 {
        let layout = layout(&mut rng);
        let action = [rng.uniform(-1.0, 1.0) as f32, rng.uniform(-1.0, 1.0) as f32];
        for flip in [[false, false], [true, false], [false, true], [true, true]] {
            // A sampler whose first draw mirrors about `flip`'s axes.
            let seed = (0..)
                .find(|&s| {
                    let bits = SplitMix64::new(s).next_u64();
                    [bits & 1 == 1, bits & 2 == 2] == flip
                })
                .unwrap();
            let mut got = second_step(&layout, action);
            mirror(&mut got, fov, &mut SplitMix64::new(seed));
            let sign = flip.map(|f| if f { -1.0 } else { 1.0 });
            let expected = second_step(
                &mirrored(&layout, flip),
                [sign[0] * action[0], sign[1] * action[1]],
            );
            assert!(!expected.centres[0].is_empty(), "spheres in view");
            assert_close(&flat(&got.centres), &flat(&expected.centres), "centres");
            assert_close(
                &flat_moves(&got.displacements),
                &flat_moves(&expected.displacements),
                "displacements",
            );
            assert_close(&got.vectors, &expected.vectors, "target vector");
            assert_close(&got.actions, &expected.actions, "action");
            assert_close(&got.rewards, &expected.rewards, "reward");
            assert_eq!(got.terminated, expected.terminated);
            assert_close(
                &flat(&got.next_centres),
                &flat(&expected.next_centres),
                "next centres",
            );
            assert_close(
                &got.next_vectors,
                &expected.next_vectors,
                "next target vector",
            );
            assert!(got.guides.iter().all(|g| g.is_nan()), "no guide stays none");
        }
    }
}
