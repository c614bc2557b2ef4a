//! The encoder's linear layer on Burn's CPU backend (flex), with a weight
//! gradient computed in place of Burn's matrix product.
//!
//! At 320 × 256 the layer maps 81,920 features to 512: its weight gradient
//! `dW = xᵀ · dy` is a 168 MB matrix summed over only the batch. Burn's
//! product allocates each output zeroed and then copies it once more to
//! align it, two extra passes over 168 MB for every network that learns.
//! Here blocks of `dW` are summed in registers and written once. The
//! forward product and the input gradient (`dx = dy · Wᵀ`, 10 MB) stay
//! Burn's. The tests check the layer against Burn's `Linear` to 1e-4,
//! forward and gradients. Other devices (wgpu, cuda) keep Burn's `Linear`.

use burn::backend::autodiff::NodeId;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, backend_extension};
use burn::tensor::Tensor;
use burn_flex::FlexTensor;
use pulp::{Arch, Simd, WithSimd};
use rayon::prelude::*;

use crate::batch_conv::tensor;

/// A linear layer with a bias.
#[backend_extension(Flex, Autodiff)]
pub trait BatchLinear: Backend {
    /// `x` `[batch, inputs]`, `weight` `[inputs, outputs]`, `bias`
    /// `[outputs]` → `x · weight + bias`, `[batch, outputs]`.
    fn batch_linear(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// `x · weight + bias` (see [`BatchLinear`]); only on devices where
/// [`is_cpu_backend`](crate::batch_conv::is_cpu_backend) holds.
pub fn batch_linear(x: Tensor<2>, weight: Tensor<2>, bias: Tensor<1>) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as BatchLinear>::batch_linear(
        x.into_dispatch(),
        weight.into_dispatch(),
        bias.into_dispatch(),
    ))
}

impl BatchLinear for Flex {
    fn batch_linear(x: FlexTensor, weight: FlexTensor, bias: FlexTensor) -> FlexTensor {
        forward(x, weight, &bias)
    }
}

/// The backward step.
#[derive(Debug)]
struct BatchLinearBackward;

impl Backward<Flex, 3> for BatchLinearBackward {
    /// The checkpointed input and weight.
    type State = (NodeId, NodeId);

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, cp: &mut Checkpointer) {
        let [node_x, node_weight, node_bias] = ops.parents;
        let dy: FlexTensor = grads.consume::<Flex>(&ops.node).to_contiguous();
        let (x, weight) = ops.state;
        let x: FlexTensor = cp.retrieve_node_output(x);
        let weight: FlexTensor = cp.retrieve_node_output(weight);
        let [batch, outputs] = dy.layout().shape().dims::<2>();
        if let Some(node) = node_x {
            let dx = burn_flex::ops::matmul::matmul(dy.clone(), weight.transpose(0, 1));
            grads.register::<Flex>(node.id, dx);
        }
        if let Some(node) = node_weight {
            let x = x.to_contiguous();
            let inputs = x.layout().shape()[1];
            let dw = weight_grad(x.storage(), dy.storage(), batch, inputs);
            grads.register::<Flex>(node.id, tensor(dw, [inputs, outputs]));
        }
        if let Some(node) = node_bias {
            let mut db = vec![0f32; outputs];
            for row in dy.storage::<f32>().chunks_exact(outputs) {
                for (d, g) in db.iter_mut().zip(row) {
                    *d += g;
                }
            }
            grads.register::<Flex>(node.id, tensor(db, [outputs]));
        }
    }
}

impl<C: CheckpointStrategy> BatchLinear for Autodiff<Flex, C> {
    fn batch_linear(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let nodes = [x.node(), weight.node(), bias.node()];
        let apply = |x: FloatTensor<Self>, weight: FloatTensor<Self>, bias: FloatTensor<Self>| {
            forward(
                x.into_primitive(),
                weight.into_primitive(),
                &bias.into_primitive(),
            )
        };
        match BatchLinearBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(mut prep) => {
                let state = (prep.checkpoint(&x), prep.checkpoint(&weight));
                prep.finish(state, apply(x, weight, bias))
            }
            OpsKind::UnTracked(prep) => prep.finish(apply(x, weight, bias)),
        }
    }
}

fn forward(x: FlexTensor, weight: FlexTensor, bias: &FlexTensor) -> FlexTensor {
    let [batch, inputs] = x.layout().shape().dims::<2>();
    let [rows, outputs] = weight.layout().shape().dims::<2>();
    assert!(
        rows == inputs && bias.layout().shape().num_elements() == outputs,
        "batch_linear: input [{batch}, {inputs}], weight [{rows}, {outputs}] and bias {:?} do not fit",
        bias.layout().shape()
    );
    let y = burn_flex::ops::matmul::matmul(x, weight).to_contiguous();
    let bias = bias.to_contiguous();
    let out = y
        .storage::<f32>()
        .chunks_exact(outputs)
        .flat_map(|row| row.iter().zip(bias.storage::<f32>()).map(|(y, b)| y + b))
        .collect();
    tensor(out, [batch, outputs])
}

/// Rows of `dW` summed together in registers.
const ROWS: usize = 4;
/// Vectors of `dW`'s columns summed together in registers.
const VECTORS: usize = 4;
/// Rows of `dW` per parallel task.
const TASK_ROWS: usize = 64;

/// `xᵀ · dy` for `x` `[batch, inputs]` and `dy` `[batch, outputs]`:
/// `[inputs, outputs]`, each element a sum over the batch in order.
fn weight_grad(x: &[f32], dy: &[f32], batch: usize, inputs: usize) -> Vec<f32> {
    let outputs = dy.len() / batch.max(1);
    let mut dw = vec![0f32; inputs * outputs];
    if outputs == 0 {
        return dw;
    }
    let factors = Factors {
        x,
        dy,
        batch,
        inputs,
        outputs,
    };
    let arch = Arch::new();
    dw.par_chunks_mut(TASK_ROWS * outputs)
        .enumerate()
        .for_each(|(task, rows)| {
            arch.dispatch(OuterProduct {
                factors,
                first_row: task * TASK_ROWS,
                dw: rows,
            })
        });
    dw
}

/// `x` `[batch, inputs]` and `dy` `[batch, outputs]`.
#[derive(Clone, Copy)]
struct Factors<'a> {
    x: &'a [f32],
    dy: &'a [f32],
    batch: usize,
    inputs: usize,
    outputs: usize,
}

/// The rows of `dW` from `first_row` on, into `dw`.
struct OuterProduct<'a> {
    factors: Factors<'a>,
    first_row: usize,
    dw: &'a mut [f32],
}

impl WithSimd for OuterProduct<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        let (f, mut row) = (self.factors, self.first_row);
        let mut blocks = self.dw.chunks_exact_mut(ROWS * f.outputs);
        for block in blocks.by_ref() {
            f.rows::<S, ROWS>(simd, row, block);
            row += ROWS;
        }
        for single in blocks.into_remainder().chunks_exact_mut(f.outputs) {
            f.rows::<S, 1>(simd, row, single);
            row += 1;
        }
    }
}

impl Factors<'_> {
    /// Rows `row..row + R` of `dW` into `out` (`R` rows).
    #[inline(always)]
    fn rows<S: Simd, const R: usize>(&self, simd: S, row: usize, out: &mut [f32]) {
        let (lanes, outputs) = (S::F32_LANES, self.outputs);
        let width = VECTORS * lanes;
        let full = outputs / width * width;
        for column in (0..full).step_by(width) {
            let mut acc = [[simd.splat_f32s(0.0); VECTORS]; R];
            for k in 0..self.batch {
                let d = &self.dy[k * outputs + column..][..width];
                let d: [S::f32s; VECTORS] =
                    std::array::from_fn(|v| simd.partial_load_f32s(&d[v * lanes..][..lanes]));
                let xs = &self.x[k * self.inputs + row..][..R];
                for (acc, &x) in acc.iter_mut().zip(xs) {
                    let x = simd.splat_f32s(x);
                    for (a, d) in acc.iter_mut().zip(d) {
                        *a = simd.mul_add_e_f32s(x, d, *a);
                    }
                }
            }
            for (r, acc) in acc.iter().enumerate() {
                let line = &mut out[r * outputs + column..][..width];
                for (v, a) in acc.iter().enumerate() {
                    simd.partial_store_f32s(&mut line[v * lanes..][..lanes], *a);
                }
            }
        }
        // The columns past the last whole block of vectors.
        for r in 0..R {
            for (j, o) in out[r * outputs..][full..outputs].iter_mut().enumerate() {
                *o = (0..self.batch)
                    .map(|k| self.x[k * self.inputs + row + r] * self.dy[k * outputs + full + j])
                    .sum();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::{Linear, LinearConfig};
    use burn::tensor::{Device, Distribution, Tolerance};

    /// Forward and all three gradients against Burn's `Linear`, on shapes
    /// with whole and partial row blocks, column blocks and tasks.
    #[test]
    fn forward_and_gradients_match_burns_linear() {
        let device = Device::flex().autodiff();
        device.seed(11);
        for (batch, inputs, outputs) in [(32, 300, 128), (5, 131, 70), (3, 4, 1), (2, 67, 512)] {
            let layer: Linear = LinearConfig::new(inputs, outputs).init(&device);
            let x = Tensor::<2>::random([batch, inputs], Distribution::Normal(0.0, 1.0), &device)
                .require_grad();
            let up = Tensor::<2>::random([batch, outputs], Distribution::Normal(0.0, 1.0), &device);
            let run = |fast: bool| {
                let (weight, bias) = (layer.weight.val(), layer.bias.as_ref().unwrap().val());
                let y = if fast {
                    batch_linear(x.clone(), weight.clone(), bias.clone())
                } else {
                    layer.forward(x.clone())
                };
                let grads = (y.clone() * up.clone()).sum().backward();
                [
                    y.into_data(),
                    x.grad(&grads).unwrap().into_data(),
                    weight.grad(&grads).unwrap().into_data(),
                    bias.grad(&grads).unwrap().into_data(),
                ]
            };
            let (burn, ours) = (run(false), run(true));
            for (what, (b, o)) in ["output", "dx", "dW", "db"]
                .iter()
                .zip(burn.iter().zip(&ours))
            {
                assert_eq!(
                    b.shape(),
                    o.shape(),
                    "{what} at {batch} × {inputs} → {outputs}"
                );
                o.assert_approx_eq::<f32>(b, Tolerance::rel_abs(1e-4, 1e-4));
            }
        }
    }

    /// Without autodiff (the TD3 targets, actors): the same output.
    #[test]
    fn inference_matches_burns_linear() {
        let device = Device::flex();
        device.seed(12);
        let layer: Linear = LinearConfig::new(90, 33).init(&device);
        let x = Tensor::<2>::random([7, 90], Distribution::Normal(0.0, 1.0), &device);
        let ours = batch_linear(
            x.clone(),
            layer.weight.val(),
            layer.bias.as_ref().unwrap().val(),
        );
        ours.into_data().assert_approx_eq::<f32>(
            &layer.forward(x).into_data(),
            Tolerance::rel_abs(1e-5, 1e-5),
        );
    }
}
