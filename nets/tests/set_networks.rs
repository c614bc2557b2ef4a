//! The set networks see a scene, not a list: shuffled centres, more
//! padding and an empty field of view are all handled as the scene says.

use burn::tensor::{Device, Tensor, TensorData};
use tweezer_gym::{EnvConfig, SplitMix64};
use tweezer_nets::{
    ActionJoin, Frame, Networks, Pooling, Scene, SetActor, SetActorConfig, SetCritic,
    SetCriticConfig, SetEncoderConfig, SetNetworks, SetShape, SphereInputs, SphereSets,
};

const FOV: [u32; 2] = [320, 256];

fn sets(max_spheres: usize, fov_px: [u32; 2]) -> SphereSets {
    let shape = SetShape {
        max_spheres,
        fov_px: FOV,
        ..SetShape::new(FOV)
    };
    SphereSets::new(&shape, fov_px)
}

fn nets(join: ActionJoin, device: &Device) -> (SetActor, SetCritic) {
    nets_pooled(Pooling::MaxMean, join, device)
}

fn nets_pooled(pooling: Pooling, join: ActionJoin, device: &Device) -> (SetActor, SetCritic) {
    let encoder = SetEncoderConfig::new()
        .with_hidden(32)
        .with_pooling(pooling);
    (
        SetActorConfig::new(encoder.clone()).init(device),
        SetCriticConfig::new(encoder)
            .with_action_join(join)
            .init(device),
    )
}

const JOINS: [ActionJoin; 3] = [
    ActionJoin::Pooled,
    ActionJoin::PerSphere,
    ActionJoin::Approach,
];

fn scene(rng: &mut SplitMix64, spheres: usize) -> Vec<[f32; 2]> {
    (0..spheres)
        .map(|_| {
            [
                rng.uniform(-10.0, 330.0) as f32,
                rng.uniform(-10.0, 266.0) as f32,
            ]
        })
        .collect()
}

/// Actions and Q values of `scenes` with sets padded to at least `pad`.
fn outputs(
    (actor, critic): &(SetActor, SetCritic),
    scenes: &[Vec<[f32; 2]>],
    pad: usize,
    device: &Device,
) -> (Vec<f32>, Vec<f32>) {
    let sets = sets(64, FOV);
    let n = scenes.len();
    let vector = || {
        let v: Vec<f32> = (0..n).flat_map(|k| [0.3, -0.2 + 0.1 * k as f32]).collect();
        Tensor::<2>::from_data(TensorData::new(v, [n, 2]), device)
    };
    let batch = || {
        let scenes = scenes.iter().map(|c| Scene::without_motion(c));
        sets.batch_padded(scenes, pad, device)
    };
    let action = actor.forward(batch(), vector());
    let q = critic.forward(batch(), vector(), action.clone());
    let values = |t: Tensor<2>| t.into_data().try_to_vec::<f32>().unwrap();
    (values(action), values(q))
}

fn assert_close(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert!((x - y).abs() <= 1e-6, "{what}: {a:?} vs {b:?}");
    }
}

#[test]
fn shuffled_centres_give_the_same_action_and_value() {
    let device = Device::flex();
    let mut rng = SplitMix64::new(7);
    let scenes: Vec<_> = (0..6).map(|k| scene(&mut rng, 3 + 4 * k)).collect();
    let shuffled: Vec<_> = scenes
        .iter()
        .map(|s| {
            let mut s = s.clone();
            for i in (1..s.len()).rev() {
                s.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
            }
            s
        })
        .collect();
    for pooling in [Pooling::MaxMean, Pooling::Max, Pooling::Mean] {
        for join in JOINS {
            let nets = nets_pooled(pooling, join, &device);
            let (a, q) = outputs(&nets, &scenes, 1, &device);
            let (b, r) = outputs(&nets, &shuffled, 1, &device);
            assert_close(&a, &b, "actions");
            assert_close(&q, &r, "values");
        }
    }
}

#[test]
fn padding_changes_nothing_and_an_empty_field_of_view_is_a_valid_input() {
    let device = Device::flex();
    let mut rng = SplitMix64::new(11);
    let scenes = vec![scene(&mut rng, 9), Vec::new(), scene(&mut rng, 1)];
    for join in JOINS {
        let nets = nets(join, &device);
        let (a, q) = outputs(&nets, &scenes, 1, &device);
        let (b, r) = outputs(&nets, &scenes, 64, &device);
        assert_close(&a, &b, "actions");
        assert_close(&q, &r, "values");
        assert!(a.iter().all(|x| x.is_finite() && x.abs() <= 1.0), "{a:?}");
        assert!(q.iter().all(|x| x.is_finite()), "{q:?}");
    }
    // Nothing in view at all: the batch's one filler row joins no set.
    let empty = vec![Vec::new(), Vec::new()];
    for join in [ActionJoin::PerSphere, ActionJoin::Approach] {
        let (_, q) = outputs(&nets(join, &device), &empty, 1, &device);
        assert!(q.iter().all(|x| x.is_finite()), "{join:?}: {q:?}");
    }
}

/// Each set of a batch is judged with its own action: an action joined to
/// the spheres of another set would make a set's value depend on its
/// neighbours in the batch.
#[test]
fn a_per_sphere_critic_joins_each_action_to_its_own_spheres() {
    for join in [ActionJoin::PerSphere, ActionJoin::Approach] {
        joins_each_action_to_its_own_spheres(join);
    }
}

fn joins_each_action_to_its_own_spheres(join: ActionJoin) {
    let device = Device::flex();
    let (_, critic) = nets(join, &device);
    let mut rng = SplitMix64::new(5);
    let scenes = [scene(&mut rng, 7), Vec::new(), scene(&mut rng, 12)];
    let sets = sets(64, FOV);
    let q = |scenes: &[Vec<[f32; 2]>], actions: &[[f32; 2]]| -> Vec<f32> {
        let n = scenes.len();
        let tensor = |v: Vec<f32>| Tensor::<2>::from_data(TensorData::new(v, [n, 2]), &device);
        let batch = sets.batch(scenes.iter().map(|c| Scene::without_motion(c)), &device);
        let vector = tensor([0.5, 0.1].repeat(n));
        let action = tensor(actions.concat());
        let q = critic.forward(batch, vector, action);
        q.into_data().try_to_vec::<f32>().unwrap()
    };
    let actions = [[0.9, -0.2], [-0.4, 0.3], [0.1, 0.8]];
    let together = q(&scenes, &actions);
    for k in 0..3 {
        let alone = q(&scenes[k..=k], &actions[k..=k]);
        assert!(
            (together[k] - alone[0]).abs() <= 1e-5,
            "{join:?}, set {k}: {} in the batch, {} alone",
            together[k],
            alone[0]
        );
    }
    // Another action for the last set moves its value, and only its.
    let other = q(&scenes, &[actions[0], actions[1], [-0.9, -0.7]]);
    assert_close(&together[..2], &other[..2], "the other sets' values");
    assert!(
        (together[2] - other[2]).abs() > 1e-6,
        "{join:?}: {together:?} vs {other:?}"
    );
}

#[test]
fn a_crowded_field_of_view_keeps_the_nearest_spheres() {
    let centres = [[0.0, 0.0], [170.0, 128.0], [160.0, 148.0]];
    let features = sets(2, FOV).features(Scene::without_motion(&centres));
    assert_eq!(features.len(), 2);
    // (10, 0) and (0, 20) px from the trap, over half the FOV width.
    assert_close(&features[0], &[10.0 / 160.0, 0.0, 10.0 / 160.0], "nearest");
    assert_close(&features[1], &[0.0, 20.0 / 160.0, 20.0 / 160.0], "second");
}

#[test]
fn a_wider_field_of_view_keeps_the_trained_scale() {
    // A sphere 10 px right of the trap reads the same in a field twice as
    // wide: the trap moves to the new centre, the scale stays the trained
    // one.
    let wide = sets(32, [640, 512]).features(Scene::without_motion(&[[330.0, 256.0], [0.0, 0.0]]));
    let trained = sets(32, FOV).features(Scene::without_motion(&[[170.0, 128.0]]));
    assert_close(&wide[0], &trained[0], "same offset");
    assert_close(
        &wide[1],
        &[-2.0, -1.6, 2.0f32.hypot(1.6)],
        "beyond the trained field",
    );
}

#[test]
fn the_motion_unit_is_the_worlds_sphere_speed_never_below_the_specs() {
    let unit = |speed: f64| {
        SetShape::motion_unit_for(&EnvConfig {
            max_sphere_speed_px: speed,
            ..EnvConfig::default()
        })
    };
    assert_eq!(SetShape::motion_unit_for(&EnvConfig::default()), 2.0);
    assert_eq!(unit(15.0), 15.0);
    // Still or slow spheres keep the spec's unit: a displacement in view is
    // then mostly the stage's, and a unit of 0 would divide by zero.
    assert_eq!(unit(0.5), 2.0);
    assert_eq!(unit(0.0), 2.0);
    let still = SetShape {
        inputs: SphereInputs::Motion,
        motion_unit_px: unit(0.0),
        ..SetShape::new(FOV)
    };
    let sets = SphereSets::new(&still, FOV);
    let features = sets.features(Scene::new(
        &[[170.0, 128.0]],
        &[Some([-10.0, 0.0])],
        [1.0, 0.0],
    ));
    assert_close(
        &features[0][3..],
        &[-5.0, 0.0, 0.0],
        "the stage's move, in the spec's unit",
    );
}

#[test]
fn motion_reads_each_displacement_and_flags_newcomers() {
    let shape = SetShape {
        inputs: SphereInputs::Motion,
        ..SetShape::new(FOV)
    };
    let sets = SphereSets::new(&shape, FOV);
    let centres = [[170.0, 128.0], [160.0, 148.0]];
    let features = sets.features(Scene::new(&centres, &[Some([1.0, -2.0]), None], [1.0, 0.0]));
    // In units of the spec's free-sphere speed, unless the shape records another.
    let step = shape.motion_unit_px;
    assert_eq!(step, 2.0);
    assert_close(
        &features[0],
        &[
            10.0 / 160.0,
            0.0,
            10.0 / 160.0,
            1.0 / step,
            -2.0 / step,
            0.0,
        ],
        "tracked",
    );
    assert_close(
        &features[1],
        &[0.0, 20.0 / 160.0, 20.0 / 160.0, 0.0, 0.0, 1.0],
        "new",
    );
    // Motion unknown: every sphere is new.
    let unknown = sets.features(Scene::without_motion(&centres));
    assert!(unknown.iter().all(|row| row[3..] == [0.0, 0.0, 1.0]));
    // Trained among spheres four times as fast: the same move reads a
    // quarter as much, and positions are unchanged.
    let fast = SphereSets::new(
        &SetShape {
            motion_unit_px: 8.0,
            ..shape
        },
        FOV,
    );
    let slow = fast.features(Scene::new(&centres, &[Some([1.0, -2.0]), None], [1.0, 0.0]));
    assert_close(&slow[0][..3], &features[0][..3], "positions");
    assert_close(
        &slow[0][3..5],
        &[1.0 / 8.0, -2.0 / 8.0],
        "in the recorded unit",
    );
}

#[test]
fn goal_inputs_turn_offset_and_motion_towards_the_target() {
    let shape = SetShape {
        inputs: SphereInputs::Goal,
        ..SetShape::new(FOV)
    };
    let sets = SphereSets::new(&shape, FOV);
    let centres = [[170.0, 128.0], [160.0, 148.0]];
    let moves = [Some([1.0, -2.0]), None];
    // The target straight down (+y): ahead is +y, and across is −x (the
    // frame's y axis, x turned a quarter to the left).
    let features = sets.features(Scene::new(&centres, &moves, [0.0, 0.5]));
    let (step, unit) = (shape.motion_unit_px, 160.0);
    assert_close(
        &features[0],
        &[
            10.0 / unit,
            0.0,
            10.0 / unit,
            1.0 / step,
            -2.0 / step,
            0.0,
            0.0,
            -10.0 / unit,
            -2.0 / step,
            -1.0 / step,
        ],
        "tracked",
    );
    assert_close(
        &features[1][6..],
        &[20.0 / unit, 0.0, 0.0, 0.0],
        "new: ahead, not moving",
    );
    // With the trap on the target the frame is the field's own.
    let on_target = sets.features(Scene::new(&centres, &moves, [0.0, 0.0]));
    assert_close(
        &on_target[0][6..],
        &on_target[0][..2]
            .iter()
            .chain(&on_target[0][3..5])
            .copied()
            .collect::<Vec<_>>(),
        "on target",
    );
    // In the goal frame the offset and displacement are turned once: the
    // added columns repeat them, not turn them again.
    let turned = SphereSets::new(
        &SetShape {
            frame: Frame::Goal,
            ..shape
        },
        FOV,
    )
    .features(Scene::new(&centres, &moves, [0.0, 0.5]));
    assert_close(
        &turned[0][..2],
        &features[0][6..8],
        "offset in the goal frame",
    );
    assert_close(
        &turned[0][3..5],
        &features[0][8..],
        "move in the goal frame",
    );
    assert_close(
        &turned[0][6..],
        &features[0][6..],
        "goal columns in the goal frame",
    );
}

/// `v` turned a quarter turn `k` times anticlockwise: exact in floats, and
/// it maps the stage's [-1, 1]² onto itself.
fn quarter_turns([x, y]: [f32; 2], k: usize) -> [f32; 2] {
    (0..k % 4).fold([x, y], |[x, y], _| [-y, x])
}

#[test]
fn in_the_goal_frame_a_turned_scene_turns_the_action_and_keeps_the_value() {
    let device = Device::flex();
    let mut rng = SplitMix64::new(23);
    let shape = SetShape {
        inputs: SphereInputs::Motion,
        frame: Frame::Goal,
        ..SetShape::new(FOV)
    };
    let networks = SetNetworks::new(shape, FOV);
    let (actor, critic) = (networks.actor(&device), networks.critic(&device));
    let trap = FOV.map(|v| 0.5 * v as f32);
    let centres = scene(&mut rng, 12);
    let moves: Vec<_> = (0..12)
        .map(|k| {
            (k % 5 != 0).then(|| [rng.uniform(-2.0, 2.0) as f32, rng.uniform(-2.0, 2.0) as f32])
        })
        .collect();
    let vectors = [[0.8, 0.1], [-0.3, 0.6], [0.05, -0.02]];
    let act = |k: usize| {
        let turned: Vec<_> = centres
            .iter()
            .map(|c| {
                let [x, y] = quarter_turns([c[0] - trap[0], c[1] - trap[1]], k);
                [x + trap[0], y + trap[1]]
            })
            .collect();
        let moved: Vec<_> = moves
            .iter()
            .map(|m| m.map(|m| quarter_turns(m, k)))
            .collect();
        let vs: Vec<_> = vectors.iter().map(|&v| quarter_turns(v, k)).collect();
        let batch = || {
            let scenes = vs.iter().map(|&v| Scene::new(&turned, &moved, v));
            networks.sets().batch(scenes, &device)
        };
        let vector =
            || Tensor::<2>::from_data(TensorData::new(vs.concat(), [vs.len(), 2]), &device);
        let action = actor.forward(batch(), vector());
        let q = critic.forward(batch(), vector(), action.clone());
        let values = |t: Tensor<2>| t.into_data().try_to_vec::<f32>().unwrap();
        (values(action), values(q))
    };
    let (action, q) = act(0);
    assert!(action.iter().any(|a| a.abs() > 1e-3), "{action:?}");
    for k in 1..4 {
        let (turned, r) = act(k);
        let expected: Vec<f32> = action
            .chunks(2)
            .flat_map(|a| quarter_turns([a[0], a[1]], k))
            .collect();
        for (a, b) in turned.iter().zip(&expected) {
            assert!(
                (a - b).abs() <= 1e-5,
                "{k} quarter turns: {turned:?} vs {expected:?}"
            );
        }
        for (a, b) in r.iter().zip(&q) {
            assert!((a - b).abs() <= 1e-4, "{k} quarter turns: {r:?} vs {q:?}");
        }
    }
}
