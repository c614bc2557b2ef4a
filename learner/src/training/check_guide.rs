//! The critics' check as the actor's guide (`td3.guide = "check"`): before
//! an actor step, the first rows of its batch are labelled with the
//! candidate the current critics prefer to the current actor's action,
//! where they prefer one ([`critic_search::better_candidates`], the rule
//! the policy applies when it acts). The actor's gradient only follows Q1
//! near its own action; the labels carry the check's choices between
//! detours into the actor, while the actors go on exploring around it.

use crate::replay::SampledTransitions;
use crate::training::td3::Td3;
use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use tweezer_nets::{Networks, Scene, critic_search};

/// Rows of each actor batch the check labels: each costs
/// [`critic_search::CANDIDATES`] passes of both critics, so all 256 would
/// cost many times the update itself.
pub const CHECKED_ROWS: usize = 32;

/// Writes into `sampled.guides` the check's candidate for each of its
/// first [`CHECKED_ROWS`] observations where the critics prefer one by
/// more than the policy's margin; every other row is left without a
/// label (NaN).
pub fn label_with_check<N: Networks>(
    td3: &Td3<N>,
    sampled: &mut SampledTransitions,
    device: &Device,
) {
    sampled.guides.fill(f32::NAN);
    let rows = CHECKED_ROWS.min(sampled.rewards.len());
    let scenes: Vec<Scene> = (0..rows)
        .map(|i| {
            let v = &sampled.vectors[2 * i..2 * i + 2];
            Scene::new(&sampled.centres[i], &sampled.displacements[i], [v[0], v[1]])
        })
        .collect();
    let networks = td3.networks();
    let input = N::valid(networks.input(scenes.iter().copied(), device));
    let vector: Vec<f32> = sampled.vectors[..2 * rows].to_vec();
    let vector = Tensor::<2>::from_data(TensorData::new(vector, [rows, 2]), device).valid();
    let actions: Vec<[f32; 2]> = N::act(&td3.policy(), input, vector)
        .into_data()
        .try_to_vec::<f32>()
        .expect("the actor outputs f32")
        .chunks_exact(2)
        .map(|a| [a[0], a[1]])
        .collect();
    let margin = critic_search::margin(Some(td3.reward_scale()));
    let better = critic_search::better_candidates(
        networks,
        &td3.critics(),
        margin,
        &scenes,
        &actions,
        device,
    );
    for (i, candidate) in better.into_iter().enumerate() {
        if let Some(candidate) = candidate {
            sampled.guides[2 * i..2 * i + 2].copy_from_slice(&candidate);
        }
    }
}
