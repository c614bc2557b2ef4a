//! The encoder's BatchNorm and the ReLU after it on Burn's CPU backend
//! (flex): in training the batch statistics and the normalisation in two
//! passes over the input, the gradient in two more; in inference (running
//! statistics) one pass.
//!
//! Burn composes a training BatchNorm of about a dozen tensor operations
//! forward and as many backward, an inference one of four, and a ReLU of
//! two each way, each a pass over the activations into a fresh tensor,
//! several of them copies that move the channels first. Here each pass
//! reads a channel's planes in place. It is the same function (biased batch
//! variance, Burn's running-statistics update, ReLU's gradient zero where
//! its output is): the tests check it against Burn's BatchNorm and ReLU to
//! 1e-4, outputs, gradients and running statistics. Other devices keep
//! Burn's.

use super::tensor;
use burn::backend::autodiff::NodeId;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, backend_extension};
use burn::nn::BatchNorm;
use burn::tensor::Tensor;
use burn_flex::FlexTensor;
use rayon::prelude::*;

/// BatchNorm with the statistics of the batch, then ReLU.
#[backend_extension(Flex, Autodiff)]
pub trait BatchNormReluTraining: Backend {
    /// `x` `[batch, channels, h, w]`, `gamma` and `beta` `[channels]` →
    /// (ReLU of the normalised `x`, the batch mean, the biased batch
    /// variance), the statistics `[channels]` and untracked.
    fn batch_norm_relu_training(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        epsilon: f64,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>);
}

/// BatchNorm with given statistics (the running ones), then ReLU.
#[backend_extension(Flex)]
pub trait BatchNormReluInference: Backend {
    /// `x` `[batch, channels, h, w]`, the rest `[channels]` → ReLU of the
    /// normalised `x`.
    fn batch_norm_relu_inference(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        variance: FloatTensor<Self>,
        epsilon: f64,
    ) -> FloatTensor<Self>;
}

/// ReLU of `layer` applied to `x` with its running statistics, as Burn's
/// [`BatchNorm::forward`] does without autodiff; only on the CPU backend
/// without autodiff.
pub fn batch_norm_relu_inference(layer: &BatchNorm, x: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(
        <Dispatch as BatchNormReluInference>::batch_norm_relu_inference(
            x.into_dispatch(),
            layer.gamma.val().into_dispatch(),
            layer.beta.val().into_dispatch(),
            layer.running_mean.value().into_dispatch(),
            layer.running_var.value().into_dispatch(),
            layer.epsilon,
        ),
    )
}

impl BatchNormReluInference for Flex {
    fn batch_norm_relu_inference(
        x: FlexTensor,
        gamma: FlexTensor,
        beta: FlexTensor,
        mean: FlexTensor,
        variance: FlexTensor,
        epsilon: f64,
    ) -> FlexTensor {
        let s = Statistics::given(&mean, &variance, epsilon);
        s.normalise(
            x,
            gamma.to_contiguous().storage(),
            beta.to_contiguous().storage(),
        )
    }
}

/// ReLU of `layer` applied to `x` in training, as Burn's
/// [`BatchNorm::forward`] does, running statistics included; only on the
/// CPU backend with autodiff (see [`crate::is_cpu_backend`]).
pub fn batch_norm_relu_training(layer: &BatchNorm, x: Tensor<4>) -> Tensor<4> {
    let (y, mean, variance) = <Dispatch as BatchNormReluTraining>::batch_norm_relu_training(
        x.into_dispatch(),
        layer.gamma.val().into_dispatch(),
        layer.beta.val().into_dispatch(),
        layer.epsilon,
    );
    let blend = |state: &burn::module::RunningState<Tensor<1>>, batch: FloatTensor<Dispatch>| {
        let batch = Tensor::<1>::from_dispatch(batch).detach();
        let running = state.value_sync().to_device(&batch.device());
        let value = running.mul_scalar(1.0 - layer.momentum) + batch.mul_scalar(layer.momentum);
        state.update(value.detach());
    };
    blend(&layer.running_mean, mean);
    blend(&layer.running_var, variance);
    Tensor::from_dispatch(y)
}

impl BatchNormReluTraining for Flex {
    fn batch_norm_relu_training(
        x: FlexTensor,
        gamma: FlexTensor,
        beta: FlexTensor,
        epsilon: f64,
    ) -> (FlexTensor, FlexTensor, FlexTensor) {
        let x = x.to_contiguous();
        let s = Statistics::of(&x, epsilon);
        let y = s.normalise(
            x,
            gamma.to_contiguous().storage(),
            beta.to_contiguous().storage(),
        );
        let channels = [s.channels];
        (y, tensor(s.mean, channels), tensor(s.variance, channels))
    }
}

/// The backward step, with the statistics the forward pass computed.
#[derive(Debug)]
struct BatchNormBackward;

impl Backward<Flex, 3> for BatchNormBackward {
    /// The checkpointed input and gamma, β, the batch mean and variance,
    /// ε.
    type State = (NodeId, NodeId, FlexTensor, FlexTensor, FlexTensor, f64);

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, cp: &mut Checkpointer) {
        let [node_x, node_gamma, node_beta] = ops.parents;
        let dy: FlexTensor = grads.consume::<Flex>(&ops.node);
        let (x, gamma, beta, mean, variance, epsilon) = ops.state;
        let x: FlexTensor = cp.retrieve_node_output(x);
        let gamma: FlexTensor = cp.retrieve_node_output(gamma);
        let x = x.to_contiguous();
        let s = Statistics::given(&mean, &variance, epsilon);
        let g = s.gradients(
            &x,
            &dy.to_contiguous(),
            (
                gamma.to_contiguous().storage(),
                beta.to_contiguous().storage(),
            ),
            node_x.is_some(),
        );
        if let (Some(node), Some(dx)) = (node_x, g.x) {
            grads.register::<Flex>(node.id, dx);
        }
        if let Some(node) = node_gamma {
            grads.register::<Flex>(node.id, g.gamma);
        }
        if let Some(node) = node_beta {
            grads.register::<Flex>(node.id, g.beta);
        }
    }
}

impl<C: CheckpointStrategy> BatchNormReluTraining for Autodiff<Flex, C> {
    fn batch_norm_relu_training(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        epsilon: f64,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let nodes = [x.node(), gamma.node(), beta.node()];
        let forward =
            |x: &FloatTensor<Self>, gamma: &FloatTensor<Self>, beta: FloatTensor<Self>| {
                <Flex as BatchNormReluTraining>::batch_norm_relu_training(
                    x.primitive().clone(),
                    gamma.primitive().clone(),
                    beta.into_primitive(),
                    epsilon,
                )
            };
        match BatchNormBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(mut prep) => {
                let (x_state, gamma_state) = (prep.checkpoint(&x), prep.checkpoint(&gamma));
                let shift = beta.primitive().clone();
                let (y, mean, variance) = forward(&x, &gamma, beta);
                let state = (
                    x_state,
                    gamma_state,
                    shift,
                    mean.clone(),
                    variance.clone(),
                    epsilon,
                );
                (
                    prep.finish(state, y),
                    FloatTensor::<Self>::new(mean),
                    FloatTensor::<Self>::new(variance),
                )
            }
            OpsKind::UnTracked(prep) => {
                let (y, mean, variance) = forward(&x, &gamma, beta);
                (
                    prep.finish(y),
                    FloatTensor::<Self>::new(mean),
                    FloatTensor::<Self>::new(variance),
                )
            }
        }
    }
}

/// Σ f(a, b) over the pairs of `a` and `b`, in eight running sums (which
/// the compiler keeps in one vector register) rather than one.
fn sum_of(a: &[f32], b: &[f32], f: impl Fn(f32, f32) -> f32) -> f32 {
    let mut lanes = [0f32; 8];
    let (a_chunks, b_chunks) = (a.chunks_exact(8), b.chunks_exact(8));
    let rest: f32 = (a_chunks.remainder().iter().zip(b_chunks.remainder()))
        .map(|(a, b)| f(*a, *b))
        .sum();
    for (a, b) in a_chunks.zip(b_chunks) {
        for ((lane, a), b) in lanes.iter_mut().zip(a).zip(b) {
            *lane += f(*a, *b);
        }
    }
    lanes.iter().sum::<f32>() + rest
}

/// max(v, 0) as Burn's ReLU: zero where `v` ≤ 0, so NaN passes.
fn relu(v: f32) -> f32 {
    if v <= 0.0 { 0.0 } else { v }
}

/// The planes of channel `c` in `x` `[batch, channels, plane]`.
fn channel_planes(
    x: &[f32],
    plane: usize,
    channels: usize,
    c: usize,
) -> impl Iterator<Item = &[f32]> {
    x.chunks_exact(plane).skip(c).step_by(channels)
}

/// A batch's statistics per channel.
struct Statistics {
    channels: usize,
    mean: Vec<f32>,
    /// Biased: divided by the number of values, as Burn's.
    variance: Vec<f32>,
    epsilon: f64,
}

/// The gradients of one BatchNorm.
struct Grads {
    x: Option<FlexTensor>,
    gamma: FlexTensor,
    beta: FlexTensor,
}

impl Statistics {
    /// Statistics already computed, `[channels]` each.
    fn given(mean: &FlexTensor, variance: &FlexTensor, epsilon: f64) -> Self {
        let values = |t: &FlexTensor| t.to_contiguous().storage::<f32>().to_vec();
        Self {
            channels: mean.layout().shape()[0],
            mean: values(mean),
            variance: values(variance),
            epsilon,
        }
    }

    /// The mean, then the variance about it (two passes, as Burn's).
    fn of(x: &FlexTensor, epsilon: f64) -> Self {
        let shape = x.layout().shape();
        assert!(
            shape.num_dims() == 4,
            "batch norm: input {shape:?} is not [batch, channels, h, w]"
        );
        let (channels, plane) = (shape[1], shape[2] * shape[3]);
        let x = x.storage::<f32>();
        let count = (x.len() / channels) as f32;
        let per_channel = |c: usize| {
            let planes = || channel_planes(x, plane, channels, c);
            let mean = planes().map(|p| sum_of(p, p, |v, _| v)).sum::<f32>() / count;
            let variance: f32 = planes()
                .map(|p| sum_of(p, p, |v, _| (v - mean) * (v - mean)))
                .sum();
            (mean, variance / count)
        };
        let (mean, variance) = (0..channels).into_par_iter().map(per_channel).unzip();
        Self {
            channels,
            mean,
            variance,
            epsilon,
        }
    }

    /// 1 / sqrt(variance + ε) of channel `c`.
    fn inverse_std(&self, c: usize) -> f32 {
        (1.0 / (f64::from(self.variance[c]) + self.epsilon).sqrt()) as f32
    }

    /// The normalisation of channel `c` as x · scale + shift: (scale,
    /// shift).
    fn affine(&self, c: usize, gamma: &[f32], beta: &[f32]) -> (f32, f32) {
        let scale = gamma[c] * self.inverse_std(c);
        (scale, beta[c] - self.mean[c] * scale)
    }

    /// ReLU of γ (x − mean) / sqrt(variance + ε) + β, written over `x`
    /// where nothing else holds it (in inference, where nothing needs the
    /// input again).
    fn normalise(&self, x: FlexTensor, gamma: &[f32], beta: &[f32]) -> FlexTensor {
        let mut y = x.to_contiguous();
        drop(x);
        let plane = y.layout().shape().num_elements() / (y.layout().shape()[0] * self.channels);
        let affine = |index: usize| self.affine(index % self.channels, gamma, beta);
        if let Some(values) = y.try_storage_mut::<f32>() {
            values
                .par_chunks_mut(plane)
                .enumerate()
                .for_each(|(index, values)| {
                    let (scale, shift) = affine(index);
                    for v in values {
                        *v = relu(*v * scale + shift);
                    }
                });
            return y;
        }
        let x = y.storage::<f32>();
        let mut out = vec![0f32; x.len()];
        out.par_chunks_mut(plane)
            .zip(x.par_chunks(plane))
            .enumerate()
            .for_each(|(index, (out, x))| {
                let (scale, shift) = affine(index);
                for (out, x) in out.iter_mut().zip(x) {
                    *out = relu(x * scale + shift);
                }
            });
        tensor(out, y.layout().shape().clone())
    }

    /// The gradients from the output gradient `dy`: with g = dy where the
    /// output is positive and 0 elsewhere (ReLU's), x̂ the normalised input
    /// and N the values per channel, dβ = Σ g, dγ = Σ g x̂, and
    /// dx = γ / sqrt(variance + ε) (g − dβ / N − x̂ dγ / N).
    fn gradients(
        &self,
        x: &FlexTensor,
        dy: &FlexTensor,
        (gamma, beta): (&[f32], &[f32]),
        input: bool,
    ) -> Grads {
        let shape = x.layout().shape().clone();
        let (x, dy) = (x.storage::<f32>(), dy.storage::<f32>());
        let channels = self.channels;
        let plane = x.len() / (shape[0] * channels);
        let count = (x.len() / channels) as f32;
        // ReLU's gradient: dy where the output x · scale + shift is positive.
        let passed = |x: f32, dy: f32, (scale, shift): (f32, f32)| {
            if relu(x * scale + shift) == 0.0 {
                0.0
            } else {
                dy
            }
        };
        let (beta_grad, gamma_grad): (Vec<f32>, Vec<f32>) = (0..channels)
            .into_par_iter()
            .map(|c| {
                let (mean, inverse_std) = (self.mean[c], self.inverse_std(c));
                let affine = self.affine(c, gamma, beta);
                let planes = |t| channel_planes(t, plane, channels, c);
                let (mut db, mut dg) = (0.0, 0.0);
                for (x, d) in planes(x).zip(planes(dy)) {
                    db += sum_of(x, d, |x, d| passed(x, d, affine));
                    dg += sum_of(x, d, |x, d| (x - mean) * inverse_std * passed(x, d, affine));
                }
                (db, dg)
            })
            .unzip();
        let dx = input.then(|| {
            let mut dx = vec![0f32; x.len()];
            dx.par_chunks_mut(plane)
                .zip(x.par_chunks(plane).zip(dy.par_chunks(plane)))
                .enumerate()
                .for_each(|(index, (dx, (x, dy)))| {
                    let c = index % channels;
                    let (mean, inverse_std) = (self.mean[c], self.inverse_std(c));
                    let affine = self.affine(c, gamma, beta);
                    let (db, dg) = (beta_grad[c] / count, gamma_grad[c] / count);
                    for ((dx, x), dy) in dx.iter_mut().zip(x).zip(dy) {
                        let normalised = (x - mean) * inverse_std;
                        *dx = affine.0 * (passed(*x, *dy, affine) - db - normalised * dg);
                    }
                });
            tensor(dx, shape)
        });
        Grads {
            x: dx,
            gamma: tensor(gamma_grad, [channels]),
            beta: tensor(beta_grad, [channels]),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::{Module, Param};
    use burn::nn::BatchNormConfig;
    use burn::tensor::{Device, Distribution, Tolerance, activation};

    fn tolerance() -> Tolerance<f32> {
        Tolerance::rel_abs(1e-4, 1e-4)
    }

    /// Burn's BatchNorm and ReLU and this one on the same input, γ and β,
    /// twice in training (the second pass starting from the running
    /// statistics the first left): outputs, gradients of a random linear
    /// function of the output and running statistics; then in inference; to
    /// 1e-4.
    fn check(shape: [usize; 4], offset: f64) {
        let device = Device::flex().autodiff();
        device.seed(5);
        let channels = shape[1];
        let random = |shape: Vec<usize>, mean: f64| {
            Tensor::<1>::random(
                [shape.iter().product::<usize>()],
                Distribution::Normal(mean, 1.0),
                &device,
            )
        };
        let gamma = random(vec![channels], 1.0);
        let beta = random(vec![channels], 0.0);
        let layer = || {
            let mut layer = BatchNormConfig::new(channels).init(&device);
            layer.gamma = Param::from_tensor(gamma.clone().detach());
            layer.beta = Param::from_tensor(beta.clone().detach());
            layer
        };
        let (plain, fast) = (layer(), layer());
        for _ in 0..2 {
            let x = random(shape.to_vec(), offset).reshape(shape).detach();
            let probe = random(shape.to_vec(), 0.0).reshape(shape).detach();
            let run = |layer: &BatchNorm, fused: bool| {
                let x = Param::from_tensor(x.clone()).val();
                let y = match fused {
                    true => batch_norm_relu_training(layer, x.clone()),
                    false => activation::relu(layer.forward(x.clone())),
                };
                let grads = (y.clone() * probe.clone()).sum().backward();
                [
                    y.into_data(),
                    x.grad(&grads).expect("input gradient").into_data(),
                    layer
                        .gamma
                        .val()
                        .grad(&grads)
                        .expect("γ gradient")
                        .into_data(),
                    layer
                        .beta
                        .val()
                        .grad(&grads)
                        .expect("β gradient")
                        .into_data(),
                    layer.running_mean.value().into_data(),
                    layer.running_var.value().into_data(),
                ]
            };
            for (fast, plain) in run(&fast, true).iter().zip(&run(&plain, false)) {
                fast.assert_approx_eq::<f32>(plain, tolerance());
            }
        }
        // Inference, with the running statistics the passes left.
        let (layer, x) = (
            plain.valid(),
            random(shape.to_vec(), offset).reshape(shape).inner(),
        );
        let expected = activation::relu(layer.forward(x.clone())).into_data();
        // Here `x` is the only handle: normalised in place.
        batch_norm_relu_inference(&layer, x)
            .into_data()
            .assert_approx_eq::<f32>(&expected, tolerance());
    }

    #[test]
    fn training_and_inference_match_burns_batch_norm_and_relu() {
        check([3, 5, 4, 6], 0.0);
        // The encoder's first layer at 40 × 32, values far from zero.
        check([4, 32, 8, 10], 3.0);
        // Planes whose length is not a multiple of the eight running sums.
        check([2, 3, 3, 3], -1.0);
    }
}
