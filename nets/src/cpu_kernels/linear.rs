//! The encoder's linear layer on Burn's CPU backend (flex), whose weight
//! gradient is registered as its two factors.
//!
//! At 320 × 256 the layer maps 81,920 features to 512: its weight gradient
//! `dW = xᵀ · dy` is a 168 MB matrix of rank at most the batch size, made
//! from 10 MB of factors. The backward step registers the factors instead
//! ([`FactoredGradient`]), and [`super::adam`]'s step expands them block
//! by block beside the weight it updates: no network that learns holds a
//! 168 MB gradient (two at once in the critics' step), and nothing writes
//! and reads one back. The forward product and the input gradient
//! (`dx = dy · Wᵀ`) stay Burn's. The tests check the layer against Burn's
//! `Linear` to 1e-4, forward and gradients (expanded). Other devices (wgpu,
//! cuda) keep Burn's `Linear`.

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

use super::tensor;

/// A linear layer with a bias.
#[backend_extension(Flex, Autodiff)]
pub trait LinearKernel: Backend {
    /// `x` `[batch, inputs]`, `weight` `[inputs, outputs]`, `bias`
    /// `[outputs]` → `x · weight + bias`, `[batch, outputs]`.
    fn linear(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// `x · weight + bias` (see [`LinearKernel`]); only on devices where
/// [`is_cpu_backend`](super::is_cpu_backend) holds. The
/// weight's gradient is a [`FactoredGradient`]: an optimiser must read it
/// as one.
pub fn linear(x: Tensor<2>, weight: Tensor<2>, bias: Tensor<1>) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as LinearKernel>::linear(
        x.into_dispatch(),
        weight.into_dispatch(),
        bias.into_dispatch(),
    ))
}

impl LinearKernel for Flex {
    fn linear(x: FlexTensor, weight: FlexTensor, bias: FlexTensor) -> FlexTensor {
        forward(x, weight, &bias)
    }
}

/// The backward step.
#[derive(Debug)]
struct LinearBackward;

impl Backward<Flex, 3> for LinearBackward {
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
            let factors = FactoredGradient::pack(x.storage(), dy.storage(), batch, inputs, outputs);
            grads.register::<Flex>(node.id, tensor(factors, [batch + 1, inputs + outputs]));
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

impl<C: CheckpointStrategy> LinearKernel for Autodiff<Flex, C> {
    fn linear(
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
        match LinearBackward
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
        "linear: input [{batch}, {inputs}], weight [{rows}, {outputs}] and bias {:?} do not fit",
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

/// The weight gradient `dW = xᵀ · dy` of the encoder's linear layer on the
/// CPU as its backward step registers it: for a weight `[inputs, outputs]`,
/// a tensor `[batch + 1, inputs + outputs]` whose row `k` is sample `k`'s
/// input and output gradient, `[x_k | dy_k]`, and whose last row is
/// `[1, 0, …]`.
///
/// Burn adds the gradients a weight gets from each of its uses; the sum of
/// two factored gradients is not one, so the `1` counts the uses: a layer
/// used twice in one graph makes it `2`, which [`FactoredGradient::of`]
/// refuses instead of expanding a wrong gradient.
#[derive(Clone, Copy, Debug)]
pub struct FactoredGradient<'a> {
    /// The tensor's elements, row by row.
    rows: &'a [f32],
    batch: usize,
    inputs: usize,
    outputs: usize,
}

/// A gradient that is not the [`FactoredGradient`] of its weight.
#[derive(Debug, thiserror::Error)]
#[error("the gradient of a {weight:?} weight is {gradient:?}: {why}")]
pub struct FactoredGradientError {
    weight: [usize; 2],
    gradient: [usize; 2],
    why: &'static str,
}

impl<'a> FactoredGradient<'a> {
    /// The factored gradient in `elements`, a tensor of shape `gradient`,
    /// registered for a weight of shape `weight`: `None` where the shapes
    /// are equal (an ordinary gradient).
    pub fn of(
        elements: &'a [f32],
        gradient: [usize; 2],
        weight: [usize; 2],
    ) -> Option<Result<Self, FactoredGradientError>> {
        if gradient == weight {
            return None;
        }
        let ([rows, width], [inputs, outputs]) = (gradient, weight);
        let fail = |why| {
            Some(Err(FactoredGradientError {
                weight,
                gradient,
                why,
            }))
        };
        if rows == 0 || width != inputs + outputs || elements.len() != rows * width {
            return fail("neither the weight's shape nor its factors'");
        }
        let batch = rows - 1;
        let last = &elements[batch * width..];
        if last[0] != 1.0 || last[1..].iter().any(|&e| e != 0.0) {
            return fail(
                "a factored gradient summed with another: the layer was used more than once in \
                 one graph, whose weight gradient cannot be kept as factors",
            );
        }
        Some(Ok(Self {
            rows: &elements[..batch * width],
            batch,
            inputs,
            outputs,
        }))
    }

    /// The tensor's elements for inputs `x` `[batch, inputs]` and output
    /// gradients `dy` `[batch, outputs]`.
    fn pack(x: &[f32], dy: &[f32], batch: usize, inputs: usize, outputs: usize) -> Vec<f32> {
        let mut elements = Vec::with_capacity((batch + 1) * (inputs + outputs));
        for k in 0..batch {
            elements.extend_from_slice(&x[k * inputs..][..inputs]);
            elements.extend_from_slice(&dy[k * outputs..][..outputs]);
        }
        elements.push(1.0);
        elements.resize((batch + 1) * (inputs + outputs), 0.0);
        elements
    }

    /// Columns of `dW` (the weight's outputs).
    pub fn outputs(&self) -> usize {
        self.outputs
    }

    /// Rows `first_row..` of `dW` into `out`, whole rows: each element the
    /// sum over the batch in order, the same for any split into rows.
    pub fn rows_into(&self, first_row: usize, out: &mut [f32]) {
        if self.outputs == 0 {
            return;
        }
        assert!(
            out.len().is_multiple_of(self.outputs)
                && first_row + out.len() / self.outputs <= self.inputs,
            "rows {first_row}.. of {} do not fill {} elements",
            self.inputs,
            out.len()
        );
        Arch::new().dispatch(OuterProduct {
            factors: *self,
            first_row,
            dw: out,
        });
    }

    /// `x[k, i]`: sample `k`'s inputs from `i` on.
    #[inline(always)]
    fn x(&self, k: usize, i: usize) -> &[f32] {
        &self.rows[k * (self.inputs + self.outputs) + i..][..self.inputs - i]
    }

    /// `dy[k, j]`: sample `k`'s output gradients from `j` on.
    #[inline(always)]
    fn dy(&self, k: usize, j: usize) -> &[f32] {
        &self.rows[k * (self.inputs + self.outputs) + self.inputs + j..][..self.outputs - j]
    }
}

/// The rows of `dW` from `first_row` on, into `dw`.
struct OuterProduct<'a> {
    factors: FactoredGradient<'a>,
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
            f.block::<S, ROWS>(simd, row, block);
            row += ROWS;
        }
        for single in blocks.into_remainder().chunks_exact_mut(f.outputs) {
            f.block::<S, 1>(simd, row, single);
            row += 1;
        }
    }
}

impl FactoredGradient<'_> {
    /// Rows `row..row + R` of `dW` into `out` (`R` rows).
    #[inline(always)]
    fn block<S: Simd, const R: usize>(&self, simd: S, row: usize, out: &mut [f32]) {
        let (lanes, outputs) = (S::F32_LANES, self.outputs);
        let width = VECTORS * lanes;
        let full = outputs / width * width;
        for column in (0..full).step_by(width) {
            let mut acc = [[simd.splat_f32s(0.0); VECTORS]; R];
            for k in 0..self.batch {
                let d = &self.dy(k, column)[..width];
                let d: [S::f32s; VECTORS] =
                    std::array::from_fn(|v| simd.partial_load_f32s(&d[v * lanes..][..lanes]));
                for (acc, &x) in acc.iter_mut().zip(&self.x(k, row)[..R]) {
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
                    .map(|k| self.x(k, row + r)[0] * self.dy(k, full + j)[0])
                    .sum();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::{Linear, LinearConfig};
    use burn::tensor::{Device, Distribution, TensorData, Tolerance};

    /// `dW` of the factored gradient `grad` for a weight of shape
    /// `weight`, expanded (in two calls, to check a split into rows), or
    /// `grad` where it is an ordinary gradient.
    fn expanded(grad: Tensor<2>, weight: [usize; 2]) -> Tensor<2> {
        let device = grad.device();
        let dims = grad.dims();
        let elements: Vec<f32> = grad.into_data().try_to_vec().unwrap();
        let Some(factored) = FactoredGradient::of(&elements, dims, weight) else {
            return Tensor::from_data(TensorData::new(elements, dims), &device);
        };
        let factored = factored.unwrap();
        let [inputs, outputs] = weight;
        let mut dw = vec![f32::NAN; inputs * outputs];
        let (first, rest) = dw.split_at_mut(inputs / 2 * outputs);
        factored.rows_into(0, first);
        factored.rows_into(inputs / 2, rest);
        Tensor::from_data(TensorData::new(dw, weight), &device)
    }

    /// Forward and all three gradients (the weight's expanded) against
    /// Burn's `Linear`, on shapes with whole and partial row blocks and
    /// column blocks.
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
                    linear(x.clone(), weight.clone(), bias.clone())
                } else {
                    layer.forward(x.clone())
                };
                let grads = (y.clone() * up.clone()).sum().backward();
                let dw = expanded(weight.grad(&grads).unwrap(), [inputs, outputs]);
                [
                    y.into_data(),
                    x.grad(&grads).unwrap().into_data(),
                    dw.into_data(),
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
        let ours = linear(
            x.clone(),
            layer.weight.val(),
            layer.bias.as_ref().unwrap().val(),
        );
        ours.into_data().assert_approx_eq::<f32>(
            &layer.forward(x).into_data(),
            Tolerance::rel_abs(1e-5, 1e-5),
        );
    }

    /// The fast layer's weight gradient is factored, and one that Burn
    /// summed from two uses of the layer is refused, not expanded.
    #[test]
    fn a_layer_used_twice_in_one_graph_has_its_gradient_refused() {
        let device = Device::flex().autodiff();
        device.seed(13);
        let layer: Linear = LinearConfig::new(6, 3).init(&device);
        let (weight, bias) = (layer.weight.val(), layer.bias.as_ref().unwrap().val());
        let x = Tensor::<2>::random([4, 6], Distribution::Normal(0.0, 1.0), &device);
        let once = linear(x.clone(), weight.clone(), bias.clone());
        let grad = |y: Tensor<2>| {
            let grad = weight.grad(&y.sum().backward()).unwrap();
            let dims = grad.dims();
            (grad.into_data().try_to_vec::<f32>().unwrap(), dims)
        };
        let (elements, dims) = grad(once);
        assert_eq!(dims, [5, 9]);
        assert!(
            FactoredGradient::of(&elements, dims, [6, 3])
                .unwrap()
                .is_ok()
        );

        let twice =
            linear(x.clone(), weight.clone(), bias.clone()) + linear(x, weight.clone(), bias);
        let (elements, dims) = grad(twice);
        let error = FactoredGradient::of(&elements, dims, [6, 3])
            .unwrap()
            .unwrap_err();
        assert!(error.to_string().contains("used more than once"), "{error}");
        // A gradient of the weight's own shape is an ordinary one.
        assert!(FactoredGradient::of(&[0.0; 18], [6, 3], [6, 3]).is_none());
    }
}
