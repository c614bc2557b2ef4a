//! The parameter updates of a TD3 step, Adam and the soft target update,
//! each one pass over a parameter on the CPU backend.
//!
//! Burn's Adam runs about ten tensor operations per parameter, the soft
//! update three, each a pass over memory into a fresh tensor: for the
//! paper's 81,920 × 512 encoder output layer, 168 MB allocations that the
//! kernel faults in and zeroes every time. Here each element is updated
//! once, in place where the tensor is not shared, with Burn's formulas and
//! Adam's state ([`AdamState`]), so checkpoints are the same either way.
//! That layer's gradient arrives as its factors ([`FactoredGradient`]) and
//! is expanded here a few rows at a time, beside the rows it updates.
//! Other devices (wgpu, cuda) run Burn's operations.

use super::is_cpu_backend;
use super::linear::FactoredGradient;
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, Flex, backend_extension};
use burn::optim::LearningRate;
use burn::optim::{Adam, AdamConfig, AdamState, AdaptiveMomentumState, Optimizer};
use burn::tensor::{Device, Tensor};
use burn_flex::FlexTensor;
use pulp::{Arch, Simd, WithSimd};
use rayon::prelude::*;

/// Elements per parallel task.
const CHUNK: usize = 1 << 14;

/// `online · tau + old · (1 − tau)`, one pass on the CPU backend.
pub fn blend<const D: usize>(online: Tensor<D>, old: Tensor<D>, tau: f64) -> Tensor<D> {
    if !is_cpu_backend(&online.device()) {
        return online * tau + old * (1.0 - tau);
    }
    Tensor::from_dispatch(<Dispatch as FusedUpdates>::fused_blend(
        online.into_dispatch(),
        old.into_dispatch(),
        tau,
    ))
}

/// Adam's constants for one step.
#[derive(Clone, Copy, Debug)]
struct Step {
    lr: f32,
    beta_1: f32,
    beta_2: f32,
    /// sqrt(1 − β₂ᵗ) / (1 − β₁ᵗ).
    factor: f32,
    /// ε · sqrt(1 − β₂ᵗ).
    epsilon: f32,
}

/// The fused updates.
#[backend_extension(Flex)]
pub trait FusedUpdates: Backend {
    /// `online · tau + old · (1 − tau)`.
    fn fused_blend(
        online: FloatTensor<Self>,
        old: FloatTensor<Self>,
        tau: f64,
    ) -> FloatTensor<Self>;

    /// One Adam step on a parameter, its gradient and moments.
    /// Returns the parameter and the two moments after the step.
    #[allow(clippy::too_many_arguments)]
    fn fused_adam_step(
        param: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        moment_1: FloatTensor<Self>,
        moment_2: FloatTensor<Self>,
        lr: f32,
        beta_1: f32,
        beta_2: f32,
        factor: f32,
        epsilon: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>);
}

impl FusedUpdates for Flex {
    fn fused_blend(online: FlexTensor, old: FlexTensor, tau: f64) -> FlexTensor {
        let (a, b) = (tau as f32, (1.0 - tau) as f32);
        let mut out = old.to_contiguous();
        drop(old);
        let online = online.to_contiguous();
        out.storage_mut::<f32>()
            .par_chunks_mut(CHUNK)
            .zip(online.storage::<f32>().par_chunks(CHUNK))
            .for_each(|(t, o)| {
                for (t, o) in t.iter_mut().zip(o) {
                    *t = *o * a + *t * b;
                }
            });
        out
    }

    fn fused_adam_step(
        param: FlexTensor,
        grad: FlexTensor,
        moment_1: FlexTensor,
        moment_2: FlexTensor,
        lr: f32,
        beta_1: f32,
        beta_2: f32,
        factor: f32,
        epsilon: f32,
    ) -> (FlexTensor, FlexTensor, FlexTensor) {
        let s = Step {
            lr,
            beta_1,
            beta_2,
            factor,
            epsilon,
        };
        // Contiguous and, once the caller's handles are gone, unique: the
        // writes below then happen in place.
        let (mut p, mut m, mut v) = (
            param.to_contiguous(),
            moment_1.to_contiguous(),
            moment_2.to_contiguous(),
        );
        drop((param, moment_1, moment_2));
        let grad = grad.to_contiguous();
        let g = grad.storage::<f32>();
        let arch = Arch::new();
        let shapes = (
            p.layout().shape().as_slice(),
            grad.layout().shape().as_slice(),
        );
        let factored = match shapes {
            (&[rows, columns], &[grad_rows, grad_columns]) => {
                FactoredGradient::of(g, [grad_rows, grad_columns], [rows, columns])
                    .map(|f| f.unwrap_or_else(|e| panic!("Adam: {e}")))
            }
            _ => None,
        };
        let (pm, mm, vm) = (
            p.storage_mut::<f32>(),
            m.storage_mut::<f32>(),
            v.storage_mut::<f32>(),
        );
        match factored {
            None => pm
                .par_chunks_mut(CHUNK)
                .zip(mm.par_chunks_mut(CHUNK))
                .zip(vm.par_chunks_mut(CHUNK))
                .zip(g.par_chunks(CHUNK))
                .for_each(|(((p, m), v), g)| arch.dispatch(AdamChunk { s, p, m, v, g })),
            // Whole rows of the gradient per task, expanded into a
            // buffer of the task's thread beside the rows they update.
            Some(factored) => {
                let rows = (CHUNK / factored.outputs().max(1)).max(1);
                let chunk = rows * factored.outputs().max(1);
                pm.par_chunks_mut(chunk)
                    .zip(mm.par_chunks_mut(chunk))
                    .zip(vm.par_chunks_mut(chunk))
                    .enumerate()
                    .for_each_init(Vec::new, |g, (task, ((p, m), v))| {
                        g.resize(g.len().max(p.len()), 0.0);
                        let g = &mut g[..p.len()];
                        factored.rows_into(task * rows, g);
                        arch.dispatch(AdamChunk { s, p, m, v, g })
                    });
            }
        }
        (p, m, v)
    }
}

/// One Adam step over a chunk of a parameter, its moments and gradient,
/// in the widest SIMD vectors the CPU has (picked at run time; the build
/// targets baseline x86-64, whose 4-wide square roots and divisions made
/// this loop compute-bound).
struct AdamChunk<'a> {
    s: Step,
    p: &'a mut [f32],
    m: &'a mut [f32],
    v: &'a mut [f32],
    g: &'a [f32],
}

impl WithSimd for AdamChunk<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        let Self { s, p, m, v, g } = self;
        let (p, p_tail) = S::as_mut_simd_f32s(p);
        let (m, m_tail) = S::as_mut_simd_f32s(m);
        let (v, v_tail) = S::as_mut_simd_f32s(v);
        let (g, g_tail) = S::as_simd_f32s(g);
        let splat = |x: f32| simd.splat_f32s(x);
        let (beta_1, one_minus_beta_1) = (splat(s.beta_1), splat(1.0 - s.beta_1));
        let (beta_2, one_minus_beta_2) = (splat(s.beta_2), splat(1.0 - s.beta_2));
        let (factor, epsilon, lr) = (splat(s.factor), splat(s.epsilon), splat(s.lr));
        let smallest = splat(f32::MIN_POSITIVE);
        // [`normal`], lane by lane.
        let flush = |x: S::f32s| {
            let subnormal = simd.less_than_f32s(simd.abs_f32s(x), smallest);
            simd.select_f32s(subnormal, splat(0.0), x)
        };
        for (((p, m), v), g) in p.iter_mut().zip(m).zip(v).zip(g) {
            let (mul, add) = (|a, b| simd.mul_f32s(a, b), |a, b| simd.add_f32s(a, b));
            *m = flush(add(mul(*m, beta_1), mul(*g, one_minus_beta_1)));
            *v = flush(add(mul(*v, beta_2), mul(mul(*g, *g), one_minus_beta_2)));
            let step = simd.div_f32s(mul(*m, factor), add(simd.sqrt_f32s(*v), epsilon));
            *p = simd.sub_f32s(*p, mul(step, lr));
        }
        let tails = p_tail.iter_mut().zip(m_tail).zip(v_tail).zip(g_tail);
        for (((p, m), v), g) in tails {
            *m = normal(*m * s.beta_1 + *g * (1.0 - s.beta_1));
            *v = normal(*v * s.beta_2 + (*g * *g) * (1.0 - s.beta_2));
            *p -= (*m * s.factor) / (v.sqrt() + s.epsilon) * s.lr;
        }
    }
}

/// `x`, or 0 where it is subnormal (below `f32::MIN_POSITIVE` in size).
/// The moments of a weight whose gradient has gone to zero decay
/// geometrically into the subnormal range (m in about 800 steps), where
/// each multiplication takes the CPU a microcode assist of a hundred cycles
/// or more: in a `quick` run Adam came to take over half the learner's
/// time. A step from such a moment moves the weight by less than 1e-30.
fn normal(x: f32) -> f32 {
    if x.abs() < f32::MIN_POSITIVE { 0.0 } else { x }
}

/// Adam with Burn's formula and state, fused on the CPU backend.
#[derive(Clone)]
pub struct FusedAdam {
    beta_1: f32,
    beta_2: f32,
    epsilon: f32,
    /// Burn's, for other devices.
    burn: Adam,
}

impl FusedAdam {
    /// Adam with β₁ 0.9, β₂ 0.999 (Burn's and PyTorch's defaults) and
    /// `epsilon`.
    pub fn new(epsilon: f32) -> Self {
        Self {
            beta_1: 0.9,
            beta_2: 0.999,
            epsilon,
            burn: AdamConfig::new().with_epsilon(epsilon).build(),
        }
    }
}

/// `grad` laid out in its logical order if it has a dimension of size one.
///
/// Burn 0.22.1's fused kernels (wgpu, cuda) compute wrong, run-to-run
/// varying elements when one input is a permuted view whose size-one
/// dimension has the innermost stride: a convolution's weight gradient
/// comes back as an NCHW view of NHWC memory, and for the first
/// convolution (one input channel) it can be `[32, 1, 8, 8]` with strides
/// `[64, 1, 8, 1]`. Burn's Adam step over such a gradient got about 88 %
/// of the weights wrong (docs/configuration.md, "Known fault"). Reshaping
/// through one dimension lays it out afresh; the values are the same.
fn settled<const D: usize>(grad: Tensor<D>) -> Tensor<D> {
    let dims = grad.dims();
    if D < 2 || !dims.contains(&1) {
        return grad;
    }
    grad.reshape([dims.iter().product::<usize>()]).reshape(dims)
}

impl Optimizer for FusedAdam {
    type State<const D: usize> = AdamState<D>;

    fn step<const D: usize>(
        &self,
        lr: LearningRate,
        tensor: Tensor<D>,
        grad: Tensor<D>,
        state: Option<Self::State<D>>,
    ) -> (Tensor<D>, Option<Self::State<D>>) {
        if !is_cpu_backend(&tensor.device()) {
            return self.burn.step(lr, tensor, settled(grad), state);
        }
        let (time, moment_1, moment_2) = match state {
            Some(AdamState { momentum }) => {
                (momentum.time + 1, momentum.moment_1, momentum.moment_2)
            }
            None => (1, tensor.zeros_like(), tensor.zeros_like()),
        };
        let t = time as i32;
        let correction_2 = (1.0 - self.beta_2.powi(t)).sqrt();
        let (param, moment_1, moment_2) = <Dispatch as FusedUpdates>::fused_adam_step(
            tensor.into_dispatch(),
            grad.into_dispatch(),
            moment_1.into_dispatch(),
            moment_2.into_dispatch(),
            lr as f32,
            self.beta_1,
            self.beta_2,
            correction_2 / (1.0 - self.beta_1.powi(t)),
            self.epsilon * correction_2,
        );
        let momentum = AdaptiveMomentumState::new(
            time,
            Tensor::from_dispatch(moment_1),
            Tensor::from_dispatch(moment_2),
        );
        (Tensor::from_dispatch(param), Some(AdamState::new(momentum)))
    }

    fn to_device<const D: usize>(state: Self::State<D>, device: &Device) -> Self::State<D> {
        Adam::to_device(state, device)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::{Linear, LinearConfig};
    use burn::optim::{GradientsParams, ModuleOptimizer};
    use burn::tensor::{Distribution, TensorData};

    /// Five steps of Burn's Adam and of this one from the same weights on
    /// the same inputs: the same weights after every step, to 1e-6.
    #[test]
    fn steps_match_burns_adam() {
        let device = Device::flex().autodiff();
        device.seed(3);
        let start: Linear = LinearConfig::new(7, 5).init(&device);
        let inputs: Vec<Tensor<2>> = (0..5)
            .map(|_| Tensor::random([4, 7], Distribution::Normal(0.0, 1.0), &device))
            .collect();
        let train = |mut optim: ModuleOptimizer| {
            let mut layer = start.clone();
            inputs
                .iter()
                .map(|x| {
                    let loss = layer.forward(x.clone()).powi_scalar(2).mean();
                    let grads = GradientsParams::from_grads(loss.backward(), &layer);
                    layer = optim.step(1e-2, layer.clone(), grads);
                    layer.weight.val().into_data()
                })
                .collect::<Vec<_>>()
        };
        let burn = train(AdamConfig::new().with_epsilon(1e-8).init());
        let fused = train(ModuleOptimizer::from(FusedAdam::new(1e-8)));
        for (b, f) in burn.iter().zip(&fused) {
            f.assert_approx_eq::<f32>(b, burn::tensor::Tolerance::rel_abs(1e-6, 1e-7));
        }
    }

    /// Steps over a factored weight gradient ([`FactoredGradient`], the
    /// CPU's for the encoder's linear layer) and over the same gradient
    /// expanded by Burn's matrix product: the same weights and moments, to
    /// 1e-6 (the two sum the batch in different orders), over two steps
    /// (the first from fresh moments), on shapes split into one and into
    /// several tasks.
    #[test]
    fn steps_over_a_factored_gradient_match_steps_over_the_dense_one() {
        let device = Device::flex();
        device.seed(5);
        let normal = Distribution::Normal(0.0, 1.0);
        for (batch, inputs, outputs) in [(5, 300, 70), (32, 1000, 33), (3, 7, 512), (1, 2, 3)] {
            let weight = Tensor::<2>::random([inputs, outputs], normal, &device);
            let factors: Vec<_> = (0..2)
                .map(|_| {
                    let x = Tensor::<2>::random([batch, inputs], normal, &device);
                    let dy = Tensor::<2>::random([batch, outputs], normal, &device);
                    let dense = x.clone().transpose().matmul(dy.clone());
                    let mut last = vec![0f32; inputs + outputs];
                    last[0] = 1.0;
                    let last =
                        Tensor::from_data(TensorData::new(last, [1, inputs + outputs]), &device);
                    let factored = Tensor::cat(vec![Tensor::cat(vec![x, dy], 1), last], 0);
                    (dense, factored)
                })
                .collect();
            let optim = FusedAdam::new(1e-8);
            let train = |factored: bool| {
                let (mut w, mut state) = (weight.clone(), None);
                for (dense, f) in &factors {
                    let grad = if factored { f.clone() } else { dense.clone() };
                    (w, state) = optim.step(1e-2, w, grad, state);
                }
                let momentum = state.unwrap().momentum;
                [w, momentum.moment_1, momentum.moment_2].map(|t| t.into_data())
            };
            let (dense, factored) = (train(false), train(true));
            for (d, f) in dense.iter().zip(&factored) {
                f.assert_approx_eq::<f32>(d, burn::tensor::Tolerance::rel_abs(1e-5, 1e-6));
            }
        }
    }

    /// A weight whose gradient has gone to zero: its moments reach zero
    /// instead of lingering in the subnormal range.
    #[test]
    fn decayed_moments_become_zero_not_subnormal() {
        let device = Device::flex();
        // Nine times four weights: whole SIMD vectors and a tail.
        let weight = Tensor::<1>::ones([36], &device);
        let grad = |g: f32| {
            let four = [g, 0.0, 1e-3, -1e-3];
            Tensor::<1>::from_data(TensorData::new(four.repeat(9), [36]), &device)
        };
        let optim = FusedAdam::new(1e-8);
        let (mut w, mut state) = optim.step(1e-3, weight, grad(1e-3), None);
        // The first moment 1e-4 · 0.9ⁿ is subnormal from n = 733 to 900.
        for _ in 0..800 {
            (w, state) = optim.step(1e-3, w, grad(0.0), state);
        }
        let momentum = state.unwrap().momentum;
        let first: Vec<f32> = momentum.moment_1.into_data().try_to_vec().unwrap();
        for decayed in first.chunks(4).map(|four| &four[..2]) {
            assert_eq!(decayed, [0.0, 0.0], "decayed first moments: {first:?}");
        }
        for m in first
            .iter()
            .chain(&momentum.moment_2.into_data().try_to_vec::<f32>().unwrap())
        {
            assert!(*m == 0.0 || m.is_normal(), "a subnormal moment: {m:e}");
        }
    }

    #[test]
    fn blends_match_burns_arithmetic() {
        let device = Device::flex();
        let online = Tensor::<2>::random([33, 700], Distribution::Normal(0.0, 1.0), &device);
        let old = Tensor::<2>::random([33, 700], Distribution::Normal(0.0, 1.0), &device);
        let plain = online.clone() * 0.005 + old.clone() * (1.0 - 0.005);
        blend(online, old, 0.005)
            .into_data()
            .assert_approx_eq::<f32>(
                &plain.into_data(),
                burn::tensor::Tolerance::rel_abs(1e-6, 1e-7),
            );
    }
}
