//! Sampled transitions become tensors whose images follow the renderer.

use burn::tensor::Device;
use tweezer_gym::{EnvConfig, ImageConfig, RandomSteps, Renderer, SplitMix64};
use tweezer_learner::minibatch::minibatch_tensors;
use tweezer_learner::replay::{Replay, ReplayConfig};

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
    let mut replay = Replay::new(ReplayConfig {
        capacity: 500,
        ..ReplayConfig::default()
    });
    let mut steps = RandomSteps::new(&config, 4, 2).unwrap();
    while replay.len() < 500 {
        replay.insert(0, &steps.next().unwrap()).unwrap();
    }
    let sampled = replay.sample(6, &mut SplitMix64::new(9)).unwrap();
    let device = Device::flex();
    let batch = minibatch_tensors(&sampled, &renderer, &device);
    assert_eq!(batch.image.dims(), [6, 1, 64, 80]);
    assert_eq!(batch.next_image.dims(), [6, 1, 64, 80]);
    assert_eq!(batch.vector.dims(), [6, 2]);
    assert_eq!(batch.reward.dims(), [6, 1]);
    let pixels: Vec<f32> = batch.image.into_data().try_to_vec().unwrap();
    let next: Vec<f32> = batch.next_image.into_data().try_to_vec().unwrap();
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
