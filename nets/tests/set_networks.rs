//! The set networks see a scene, not a list: shuffled centres, more
//! padding and an empty field of view are all handled as the scene says.

use burn::tensor::{Device, Tensor, TensorData};
use tweezer_gym::SplitMix64;
use tweezer_nets::{
    SetActor, SetActorConfig, SetCritic, SetCriticConfig, SetEncoderConfig, SphereSets,
};

const FOV: [f32; 2] = [320.0, 256.0];

fn nets(device: &Device) -> (SetActor, SetCritic) {
    let encoder = SetEncoderConfig::new().with_hidden(32);
    (
        SetActorConfig::new(encoder.clone()).init(device),
        SetCriticConfig::new(encoder).init(device),
    )
}

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

/// Actions and Q values of `scenes` with sets of `max_spheres`.
fn outputs(
    (actor, critic): &(SetActor, SetCritic),
    scenes: &[Vec<[f32; 2]>],
    max_spheres: usize,
    device: &Device,
) -> (Vec<f32>, Vec<f32>) {
    let sets = SphereSets {
        fov_px: FOV,
        max_spheres,
    };
    let n = scenes.len();
    let vector = || {
        let v: Vec<f32> = (0..n).flat_map(|k| [0.3, -0.2 + 0.1 * k as f32]).collect();
        Tensor::<2>::from_data(TensorData::new(v, [n, 2]), device)
    };
    let batch = || sets.batch(scenes.iter().map(Vec::as_slice), device);
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
    let nets = nets(&device);
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
    let (a, q) = outputs(&nets, &scenes, 32, &device);
    let (b, r) = outputs(&nets, &shuffled, 32, &device);
    assert_close(&a, &b, "actions");
    assert_close(&q, &r, "values");
}

#[test]
fn padding_changes_nothing_and_an_empty_field_of_view_is_a_valid_input() {
    let device = Device::flex();
    let nets = nets(&device);
    let mut rng = SplitMix64::new(11);
    let scenes = vec![scene(&mut rng, 9), Vec::new(), scene(&mut rng, 1)];
    let (a, q) = outputs(&nets, &scenes, 16, &device);
    let (b, r) = outputs(&nets, &scenes, 64, &device);
    assert_close(&a, &b, "actions");
    assert_close(&q, &r, "values");
    assert!(a.iter().all(|x| x.is_finite() && x.abs() <= 1.0), "{a:?}");
    assert!(q.iter().all(|x| x.is_finite()), "{q:?}");
}

#[test]
fn a_crowded_field_of_view_keeps_the_nearest_spheres() {
    let sets = SphereSets {
        fov_px: FOV,
        max_spheres: 2,
    };
    let (mut features, mut mask) = (vec![0.0; 6], vec![0.0; 2]);
    sets.write(
        &[[0.0, 0.0], [170.0, 128.0], [160.0, 148.0]],
        &mut features,
        &mut mask,
    );
    assert_eq!(mask, [1.0, 1.0]);
    // (10, 0) and (0, 20) px from the trap, over half the FOV width.
    assert_close(
        &features[..3],
        &[10.0 / 160.0, 0.0, 10.0 / 160.0],
        "nearest",
    );
    assert_close(&features[3..], &[0.0, 20.0 / 160.0, 20.0 / 160.0], "second");
}
