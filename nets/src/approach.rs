//! Where the trap, held at an action, would pass each sphere: the
//! geometry of a collision, which [`crate::ActionJoin::Approach`] gives the
//! critic's per-sphere layers instead of leaving them to learn it from the
//! offset and the action.
//!
//! Dot and cross products of two vectors turned alike do not change, so the
//! same rule holds in the stage's frame and in the goal frame.

use crate::goal_frame::columns;
use burn::tensor::Tensor;

/// Values per sphere that [`passing`] gives.
pub(crate) const PASSING_FEATURES: usize = 3;

/// The miss distance's scale against the offsets': offsets run in half the
/// trained field's width (640 px), a collision is 54 px away. At 8 a unit
/// of miss is 80 px, so a first layer initialised for unit inputs tells a
/// near miss from a hit.
const MISS_SCALE: f32 = 8.0;

/// The least speed an action is divided by (in action units): a trap
/// nearly at rest passes nothing, and the features stay smooth through 0.
const SPEED_FLOOR: f32 = 0.1;

/// For each sphere at `offsets` from the trap and the action the trap holds
/// (one row each): how far ahead along the action the trap comes closest
/// to it (negative: behind), and its distance to the side of the action's
/// line there, signed and unsigned, over [`MISS_SCALE`]'s unit.
///
/// # Shapes
/// - `offsets`, `actions`: `[spheres, 2]`
/// - output: `[spheres, PASSING_FEATURES]`
pub(crate) fn passing(offsets: Tensor<2>, actions: Tensor<2>) -> Tensor<2> {
    let ([dx, dy], [ax, ay]) = (columns(offsets), columns(actions));
    let speed = (ax.clone().powi_scalar(2) + ay.clone().powi_scalar(2))
        .add_scalar(SPEED_FLOOR * SPEED_FLOOR)
        .sqrt(); // [spheres, 1]
    let along = (dx.clone() * ax.clone() + dy.clone() * ay.clone()) / speed.clone();
    let across = (dy * ax - dx * ay) / speed * MISS_SCALE;
    Tensor::cat(vec![along, across.clone(), across.abs()], 1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};

    fn rows(v: &[[f32; 2]], device: &Device) -> Tensor<2> {
        Tensor::from_data(TensorData::new(v.concat(), [v.len(), 2]), device)
    }

    #[test]
    fn a_sphere_on_the_line_is_missed_by_nothing_and_one_aside_by_its_offset() {
        let device = Device::flex();
        // Full speed along x; then along y, the scene turned with it.
        let offsets = rows(&[[0.5, 0.0], [0.3, 0.1], [-0.2, -0.05]], &device);
        let actions = rows(&[[1.0, 0.0]; 3], &device);
        let turned = rows(&[[0.0, 0.5], [-0.1, 0.3], [0.05, -0.2]], &device);
        let up = rows(&[[0.0, 1.0]; 3], &device);
        let speed = (1.0f32 + SPEED_FLOOR * SPEED_FLOOR).sqrt();
        let expected =
            [[0.5, 0.0, 0.0], [0.3, 0.8, 0.8], [-0.2, -0.4, 0.4]].map(|row| row.map(|v| v / speed));
        for got in [passing(offsets, actions), passing(turned, up)] {
            let got = got.into_data().try_to_vec::<f32>().unwrap();
            for (g, e) in got.iter().zip(expected.concat()) {
                assert!((g - e).abs() < 1e-5, "{got:?} against {expected:?}");
            }
        }
    }

    #[test]
    fn a_trap_at_rest_passes_nothing_and_stays_finite() {
        let device = Device::flex();
        let got = passing(rows(&[[0.4, -0.3]], &device), rows(&[[0.0, 0.0]], &device));
        let got = got.into_data().try_to_vec::<f32>().unwrap();
        assert_eq!(got, vec![0.0, 0.0, 0.0]);
    }
}
