//! Sampled transitions → the tensors TD3 trains on. Images are rendered by
//! the shared renderer straight into the buffers that become the tensors.

use crate::replay::SampledTransitions;
use crate::td3::Minibatch;
use burn::tensor::{Device, Tensor, TensorData};
use tweezer_gym::Renderer;
use tweezer_nets::render_images;

/// Renders every observation of `sampled` and moves the batch to `device`.
pub fn minibatch_tensors(
    sampled: &SampledTransitions,
    renderer: &Renderer,
    device: &Device,
) -> Minibatch {
    let n = sampled.rewards.len();
    let images = |centres: &[Vec<[f32; 2]>]| {
        render_images(renderer, centres.iter().map(Vec::as_slice), device)
    };
    let pairs = |v: &[f32]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [n, 2]), device);
    let column = |v: &[f32]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [n, 1]), device);
    Minibatch {
        image: images(&sampled.centres),
        vector: pairs(&sampled.vectors),
        action: pairs(&sampled.actions),
        reward: column(&sampled.rewards),
        terminated: column(&sampled.terminated),
        next_image: images(&sampled.next_centres),
        next_vector: pairs(&sampled.next_vectors),
    }
}
