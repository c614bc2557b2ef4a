//! Sampled transitions become tensors whose images follow the renderer, or
//! sets whose features follow the sphere sets, motion included.

use burn::tensor::Device;
use tweezer_gym::{EnvConfig, ImageConfig, RandomSteps, Renderer, SplitMix64};
use tweezer_learner::replay::SampledTransitions;
use tweezer_learner::replay::{Replay, ReplayConfig};
use tweezer_learner::training::minibatch::minibatch_tensors;
use tweezer_nets::{PaperNetworks, Scene, SetNetworks, SetShape, SphereInputs};

fn sampled(config: &EnvConfig) -> SampledTransitions {
    let mut replay = Replay::new(ReplayConfig {
        capacity: 500,
        ..ReplayConfig::default()
    });
    let mut steps = RandomSteps::new(config, 4, 2).unwrap();
    while replay.len() < 500 {
        replay.insert(0, &steps.next().unwrap()).unwrap();
    }
    replay.sample(6, &mut SplitMix64::new(9)).unwrap()
}

#[test]
fn sampled_batches_render_into_tensors() {
    let config = EnvConfig {
        image: ImageConfig {
            width: 80,
            height: 64,
        },
        ..EnvConfig::default()
    };
    let renderer = Renderer::for_config(&config).unwrap();
    let sampled = sampled(&config);
    let device = Device::flex();
    let networks = PaperNetworks::new(renderer.clone());
    let batch = minibatch_tensors(&sampled, &networks, &device);
    assert_eq!(batch.input.dims(), [6, 1, 64, 80]);
    assert_eq!(batch.next_input.dims(), [6, 1, 64, 80]);
    assert_eq!(batch.vector.dims(), [6, 2]);
    assert_eq!(batch.reward.dims(), [6, 1]);
    let pixels: Vec<f32> = batch.input.into_data().try_to_vec().unwrap();
    let next: Vec<f32> = batch.next_input.into_data().try_to_vec().unwrap();
    let mut expected = vec![0f32; renderer.pixels()];
    for i in 0..6 {
        let slot = i * renderer.pixels()..(i + 1) * renderer.pixels();
        renderer.render(&sampled.centres[i], &mut expected).unwrap();
        assert_eq!(&pixels[slot.clone()], &expected[..]);
        renderer
            .render(&sampled.next_centres[i], &mut expected)
            .unwrap();
        assert_eq!(&next[slot], &expected[..]);
    }
    let rewards: Vec<f32> = batch.reward.into_data().try_to_vec().unwrap();
    assert_eq!(rewards, sampled.rewards);
}

#[test]
fn sampled_batches_become_sets_without_rendering() {
    let config = EnvConfig::default();
    let sampled = sampled(&config);
    let shape = SetShape {
        inputs: SphereInputs::Motion,
        ..SetShape::new(config.fov_px)
    };
    let networks = SetNetworks::new(shape, config.fov_px);
    let batch = minibatch_tensors(&sampled, &networks, &Device::flex());
    let moving = sampled.displacements.iter().flatten().flatten().count();
    assert!(moving > 0, "the replay keeps the spheres' displacements");
    let longest = sampled.centres.iter().map(Vec::len).max().unwrap();
    assert!(longest > 0, "a dense field shows spheres");
    let set = batch.input;
    assert_eq!((set.len(), set.width), (6, longest));
    let features: Vec<f32> = set.spheres.into_data().try_to_vec().unwrap();
    let slots: Vec<i64> = set.slots.into_data().convert::<i64>().try_to_vec().unwrap();
    let counts: Vec<f32> = set.counts.into_data().try_to_vec().unwrap();
    let padding = (features.len() / 6) as i64;
    for (i, centres) in sampled.centres.iter().enumerate() {
        let v = &sampled.vectors[2 * i..2 * i + 2];
        let scene = Scene::new(centres, &sampled.displacements[i], [v[0], v[1]]);
        let expected = networks.sets().features(scene);
        assert_eq!(counts[i], expected.len().max(1) as f32);
        for k in 0..longest {
            let slot = slots[i * longest + k];
            match expected.get(k) {
                Some(f) => {
                    let row = slot as usize;
                    assert_eq!(&features[row * 6..row * 6 + 6], &f[..]);
                }
                None => assert_eq!(slot, padding),
            }
        }
    }
}
