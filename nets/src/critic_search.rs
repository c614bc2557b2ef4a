//! The actor's action checked against the learner's critics: the critics
//! value a fixed fan of candidate actions around it and the policy takes
//! the one both value most, where they value it a margin above the actor's
//! own. The actor alone must fit the choice between
//! detours into one pooled summary; the critics judge each candidate
//! against every sphere it passes, so they catch the collisions the actor
//! misses (`docs/training.md`, "The critics' check").

use crate::networks::Networks;
use crate::spheres::Scene;
use burn::tensor::{Device, Tensor, TensorData};
use tweezer_gym::Observation;

/// How much more reward than the actor's own action the critics must
/// promise a candidate before the policy takes it instead: about five
/// steps' reward on the ideal straight run. The largest of 64 noisy values
/// is biased upward, most where the critics know little, so without a
/// margin the check trades the actor's straight run for detours the
/// critics only seem to prefer (`docs/training.md`, "The check's margin").
pub const MARGIN_REWARD: f64 = 50.0;

/// [`MARGIN_REWARD`] in the units of critics whose values are rewards
/// times `reward_scale`; none where the scale is unknown (snapshots from
/// before it was recorded were measured without).
pub fn margin(reward_scale: Option<f64>) -> f32 {
    reward_scale.map_or(0.0, |scale| (MARGIN_REWARD * scale) as f32)
}

/// Candidates valued per observation.
pub const CANDIDATES: usize = 64;

/// Turns of the actor's action tried each way, in degrees.
const TURNS_DEG: [f32; 7] = [10.0, 20.0, 30.0, 45.0, 60.0, 90.0, 120.0];

/// Headings tried at full and half speed, evenly spaced.
const HEADINGS: usize = 24;

/// The candidates for the actor's action `actor`, which comes first: it
/// turned each way by [`TURNS_DEG`], [`HEADINGS`] headings at full speed
/// (on the edge of the action box) and at half speed, and standing still;
/// every one inside the action box.
pub fn candidates(actor: [f32; 2]) -> [[f32; 2]; CANDIDATES] {
    let mut all = [[0.0; 2]; CANDIDATES];
    all[0] = actor;
    let turned = TURNS_DEG.iter().flat_map(|d| [*d, -d]).map(|d| {
        let (sin, cos) = d.to_radians().sin_cos();
        [
            actor[0] * cos - actor[1] * sin,
            actor[0] * sin + actor[1] * cos,
        ]
    });
    let headings = (0..HEADINGS).flat_map(|k| {
        let (sin, cos) = (k as f32 * std::f32::consts::TAU / HEADINGS as f32).sin_cos();
        let edge = cos.abs().max(sin.abs());
        [
            [cos / edge, sin / edge],
            [0.5 * cos / edge, 0.5 * sin / edge],
        ]
    });
    // The last slot stays [0, 0]: standing still.
    for (slot, [x, y]) in all[1..].iter_mut().zip(turned.chain(headings)) {
        *slot = [x.clamp(-1.0, 1.0), y.clamp(-1.0, 1.0)];
    }
    all
}

/// For each observation, the candidate around the actor's action (`actions`,
/// one per observation) that the smaller of the two critics' values ranks
/// highest; the actor's own action where none is valued more than `margin`
/// (in the critics' units, [`margin`]) above it, where the critics give
/// NaN, and where the action itself is not finite (a broken actor is not
/// steered by its critics).
pub fn choose<N: Networks>(
    networks: &N,
    critics: &[N::Critic; 2],
    margin: f32,
    observations: &[&Observation],
    actions: &[[f32; 2]],
    device: &Device,
) -> Vec<[f32; 2]> {
    let n = observations.len();
    let rows = n * CANDIDATES;
    let tried: Vec<[[f32; 2]; CANDIDATES]> = actions.iter().map(|a| candidates(*a)).collect();
    let repeated: Vec<&Observation> = observations
        .iter()
        .flat_map(|o| std::iter::repeat_n(*o, CANDIDATES))
        .collect();
    let input = networks.input(repeated.iter().map(|o| Scene::of(o)), device);
    let vectors: Vec<f32> = repeated.iter().flat_map(|o| o.vector).collect();
    let vector = Tensor::<2>::from_data(TensorData::new(vectors, [rows, 2]), device);
    let flat: Vec<f32> = tried.iter().flatten().flatten().copied().collect();
    let action = Tensor::<2>::from_data(TensorData::new(flat, [rows, 2]), device);
    let values = critics.each_ref().map(|critic| {
        let features = N::features(critic, input.clone());
        N::value(critic, features, vector.clone(), action.clone())
            .into_data()
            .try_to_vec::<f32>()
            .expect("the critic outputs f32")
    });
    tried
        .iter()
        .enumerate()
        .map(|(i, tried)| {
            if !tried[0].iter().all(|v| v.is_finite()) {
                return tried[0];
            }
            let value = |j: usize| values[0][i * CANDIDATES + j].min(values[1][i * CANDIDATES + j]);
            let best =
                (1..CANDIDATES).fold(0, |best, j| if value(j) > value(best) { j } else { best });
            if value(best) > value(0) + margin {
                tried[best]
            } else {
                tried[0]
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn candidates_start_with_the_actors_action_and_stay_in_the_box() {
        let all = candidates([0.6, -0.8]);
        assert_eq!(all[0], [0.6, -0.8]);
        assert_eq!(all[CANDIDATES - 1], [0.0, 0.0]);
        assert!(all.iter().flatten().all(|v| (-1.0..=1.0).contains(v)));
        // Turned by 90° each way: the perpendiculars.
        let (left, right) = (all[11], all[12]);
        assert!((left[0] - 0.8).abs() < 1e-6 && (left[1] - 0.6).abs() < 1e-6);
        assert!((right[0] + 0.8).abs() < 1e-6 && (right[1] + 0.6).abs() < 1e-6);
        // Full speed straight ahead along x, then half that.
        assert_eq!((all[15], all[16]), ([1.0, 0.0], [0.5, 0.0]));
        let distinct: std::collections::BTreeSet<_> = all
            .iter()
            .map(|[x, y]| (x.to_bits(), y.to_bits()))
            .collect();
        assert_eq!(distinct.len(), CANDIDATES);
    }
}
