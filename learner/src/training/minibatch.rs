//! Sampled transitions → the tensors TD3 trains on: the networks' inputs
//! (images rendered by the shared renderer, or sphere sets) straight from
//! the replay's centres and displacements, and the guide's actions with a
//! mask of the rows that have one.

use crate::replay::SampledTransitions;
use crate::training::td3::Minibatch;
use burn::tensor::{Device, Tensor, TensorData};
use tweezer_nets::{Networks, Scene};

/// The inputs of every observation of `sampled`, on `device`.
pub fn minibatch_tensors<N: Networks>(
    sampled: &SampledTransitions,
    networks: &N,
    device: &Device,
) -> Minibatch<N::Input> {
    let n = sampled.rewards.len();
    let input =
        |centres: &[Vec<[f32; 2]>], displacements: &[Vec<Option<[f32; 2]>>], vectors: &[f32]| {
            let scenes = (centres
                .iter()
                .zip(displacements)
                .zip(vectors.chunks_exact(2)))
            .map(|((c, d), v)| Scene::new(c, d, [v[0], v[1]]));
            networks.input(scenes, device)
        };
    let pairs = |v: &[f32]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [n, 2]), device);
    let column = |v: &[f32]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [n, 1]), device);
    let guided: Vec<f32> = (sampled.guides.chunks(2))
        .map(|g| if g[0].is_nan() { 0.0 } else { 1.0 })
        .collect();
    let guides: Vec<f32> = (sampled.guides.iter())
        .map(|&g| if g.is_nan() { 0.0 } else { g })
        .collect();
    Minibatch {
        input: input(&sampled.centres, &sampled.displacements, &sampled.vectors),
        vector: pairs(&sampled.vectors),
        action: pairs(&sampled.actions),
        reward: column(&sampled.rewards),
        terminated: column(&sampled.terminated),
        steps: column(&sampled.steps),
        next_input: input(
            &sampled.next_centres,
            &sampled.next_displacements,
            &sampled.next_vectors,
        ),
        next_vector: pairs(&sampled.next_vectors),
        guide: pairs(&guides),
        guided: column(&guided),
    }
}
