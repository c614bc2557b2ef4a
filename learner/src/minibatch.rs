//! Sampled transitions → the tensors TD3 trains on: the networks' inputs
//! (images rendered by the shared renderer, or sphere sets) straight from
//! the replay's centres and displacements.

use crate::replay::SampledTransitions;
use crate::td3::Minibatch;
use burn::tensor::{Device, Tensor, TensorData};
use tweezer_nets::{Networks, Scene};

/// The inputs of every observation of `sampled`, on `device`.
pub fn minibatch_tensors<N: Networks>(
    sampled: &SampledTransitions,
    networks: &N,
    device: &Device,
) -> Minibatch<N::Input> {
    let n = sampled.rewards.len();
    let input = |centres: &[Vec<[f32; 2]>], displacements: &[Vec<Option<[f32; 2]>>]| {
        let scenes = centres
            .iter()
            .zip(displacements)
            .map(|(c, d)| Scene::new(c, d));
        networks.input(scenes, device)
    };
    let pairs = |v: &[f32]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [n, 2]), device);
    let column = |v: &[f32]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [n, 1]), device);
    Minibatch {
        input: input(&sampled.centres, &sampled.displacements),
        vector: pairs(&sampled.vectors),
        action: pairs(&sampled.actions),
        reward: column(&sampled.rewards),
        terminated: column(&sampled.terminated),
        next_input: input(&sampled.next_centres, &sampled.next_displacements),
        next_vector: pairs(&sampled.next_vectors),
    }
}
