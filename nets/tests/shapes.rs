//! The networks' shapes and ranges at the paper's and a small resolution.

use burn::tensor::{Device, Distribution, Tensor};
use tweezer_nets::{ActorConfig, CriticConfig, EncoderConfig};

fn inputs(batch: usize, h: usize, w: usize, device: &Device) -> (Tensor<4>, Tensor<2>) {
    let image = Tensor::<4>::random([batch, 1, h, w], Distribution::Bernoulli(0.1), device);
    let vector = Tensor::<2>::random([batch, 2], Distribution::Uniform(-1.0, 1.0), device);
    (image, vector)
}

#[test]
fn actor_and_critic_shapes() {
    let device = Device::flex();
    for (h, w) in [(64, 80), (256, 320)] {
        let encoder = EncoderConfig::new(h, w);
        let actor = ActorConfig::new(encoder.clone()).init(&device);
        let critic = CriticConfig::new(encoder).init(&device);
        let (image, vector) = inputs(3, h, w, &device);
        let action = actor.forward(image.clone(), vector.clone());
        assert_eq!(action.dims(), [3, 2]);
        let values: Vec<f32> = action.clone().into_data().try_to_vec::<f32>().unwrap();
        assert!(
            values
                .iter()
                .all(|v| v.is_finite() && (-1.0..=1.0).contains(v)),
            "{values:?}"
        );
        let q = critic.forward(image, vector, action);
        assert_eq!(q.dims(), [3, 1]);
    }
}
