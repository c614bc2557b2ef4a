//! Sampled transitions → the tensors TD3 trains on: the networks' inputs
//! (images rendered by the shared renderer, or sphere sets) straight from
//! the replay's centres.

use crate::replay::SampledTransitions;
use crate::td3::Minibatch;
use burn::tensor::{Device, Tensor, TensorData};
use tweezer_nets::Networks;

/// The inputs of every observation of `sampled`, on `device`.
pub fn minibatch_tensors<N: Networks>(
    sampled: &SampledTransitions,
    networks: &N,
    device: &Device,
) -> Minibatch<N::Input> {
    let n = sampled.rewards.len();
    let input =
        |centres: &[Vec<[f32; 2]>]| networks.input(centres.iter().map(Vec::as_slice), device);
    let pairs = |v: &[f32]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [n, 2]), device);
    let column = |v: &[f32]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [n, 1]), device);
    Minibatch {
        input: input(&sampled.centres),
        vector: pairs(&sampled.vectors),
        action: pairs(&sampled.actions),
        reward: column(&sampled.rewards),
        terminated: column(&sampled.terminated),
        next_input: input(&sampled.next_centres),
        next_vector: pairs(&sampled.next_vectors),
    }
}
