//! The goal frame ([`crate::Frame::Goal`]): axes turned so that x points
//! at the target. One rule, for a scene's rows as they are built and for
//! the vector and action tensors inside the networks.

use burn::tensor::Tensor;

/// `v`, given along the stage's axes, along and across the unit `heading`.
pub(crate) fn to_goal([x, y]: [f32; 2], [ux, uy]: [f32; 2]) -> [f32; 2] {
    [x * ux + y * uy, y * ux - x * uy]
}

/// [`to_goal`] of each row.
///
/// # Shapes
/// - `v`, `heading`, output: `[batch, 2]`
pub(crate) fn rows_to_goal(v: Tensor<2>, heading: Tensor<2>) -> Tensor<2> {
    let ([x, y], [ux, uy]) = (columns(v), columns(heading));
    Tensor::cat(
        vec![
            x.clone() * ux.clone() + y.clone() * uy.clone(),
            y * ux - x * uy,
        ],
        1,
    )
}

/// The inverse of [`rows_to_goal`]: rows given along and across each
/// heading, along the stage's axes.
pub(crate) fn rows_from_goal(v: Tensor<2>, heading: Tensor<2>) -> Tensor<2> {
    let ([along, across], [ux, uy]) = (columns(v), columns(heading));
    Tensor::cat(
        vec![
            along.clone() * ux.clone() - across.clone() * uy.clone(),
            along * uy + across * ux,
        ],
        1,
    )
}

pub(crate) fn columns(v: Tensor<2>) -> [Tensor<2>; 2] {
    [v.clone().narrow(1, 0, 1), v.narrow(1, 1, 1)]
}
