//! Updating Burn modules the way TD3 needs, around three properties of
//! Burn: an optimiser step consumes the module, BatchNorm keeps each
//! thread's running statistics apart until they are read, and gradients
//! come per loss. Each helper says which it answers.

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::{Gradients, Tensor};
use tweezer_nets::cpu_kernels::blend;

/// One optimiser step of `module` with `grads` at learning rate `lr`.
/// The module is moved out for the step and `stand_in` (handles to another
/// module's tensors) holds its place: the step is then the only owner of
/// the module's tensors and writes them in place instead of copying them.
pub fn step_in_place<M: Module>(
    module: &mut M,
    stand_in: M,
    optim: &mut ModuleOptimizer,
    lr: f64,
    grads: GradientsParams,
) {
    let owned = std::mem::replace(module, stand_in);
    *module = optim.step(lr, owned, grads);
}

/// [`soft_update`] of `target` towards `online`, in place.
pub fn soft_update_in_place<M: Module>(target: &mut M, online: &M, tau: f64) {
    let old = std::mem::replace(target, online.valid());
    *target = soft_update(online, old, tau);
}

/// θ' ← τ θ + (1 − τ) θ', written over the target's tensors where nothing
/// else holds them. The result starts as an inference copy of the online
/// module, so BatchNorm running statistics follow the online ones.
pub fn soft_update<M: Module>(online: &M, target: M, tau: f64) -> M {
    let mut old = Drain(Vec::new());
    drop(target.map(&mut old));
    online.valid().map(&mut Blend {
        old: old.0.into_iter(),
        tau,
    })
}

/// Twin critics' gradients in one set, for the optimiser that steps both:
/// each loss's backward pass ran alone, so `grads_1` holds `q1`'s
/// gradients and `grads_2` `q2`'s.
pub fn merged_gradients<M: Module>(
    grads_1: Gradients,
    q1: &M,
    grads_2: Gradients,
    q2: &M,
) -> GradientsParams {
    let mut into = GradientsParams::from_grads(grads_1, q1);
    q2.visit(&mut Merge {
        from: GradientsParams::from_grads(grads_2, q2),
        into: &mut into,
    });
    into
}

/// Folds the BatchNorm running statistics that `module`'s last forward
/// pass left pending into their values. Burn keeps each thread's update
/// apart until something reads them all, and a training-mode forward pass
/// reads only its own thread's: a step on another rayon worker than the
/// last one would otherwise start from stale statistics, and the two
/// threads' values would later be averaged.
pub fn settle_running_statistics<M: Module>(module: &M) {
    drop(module.valid());
}

/// A one-element tensor's value.
pub fn scalar<const D: usize>(t: &Tensor<D>) -> f64 {
    f64::from(t.clone().into_scalar::<f32>())
}

/// Moves the gradients of the visited module's parameters from `from`
/// into `into`.
struct Merge<'a> {
    from: GradientsParams,
    into: &'a mut GradientsParams,
}

impl ModuleVisitor for Merge<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if let Some(grad) = self.from.remove::<D>(param.id) {
            self.into.register(param.id, grad);
        }
    }
}

/// Takes every float parameter out of a module, flattened, in visiting
/// order, leaving one-element stand-ins in the module.
struct Drain(Vec<Tensor<1>>);

impl ModuleMapper for Drain {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let (id, t, mapper) = param.consume();
        let stand_in = Tensor::zeros([1; D], &t.device());
        let n = t.shape().num_elements();
        self.0.push(t.reshape([n]));
        Param::from_mapped_value(id, stand_in, mapper)
    }
}

/// Blends each parameter with the target's old value.
struct Blend {
    old: std::vec::IntoIter<Tensor<1>>,
    tau: f64,
}

impl ModuleMapper for Blend {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let (id, online, mapper) = param.consume();
        let old = self
            .old
            .next()
            .expect("target and online modules have the same parameters")
            .reshape(online.shape());
        let blended = blend(online, old, self.tau);
        Param::from_mapped_value(id, blended, mapper)
    }
}
