//! The kernels Burn's CPU backend (flex) runs in place of Burn's own
//! operations: the encoder's convolutions, its linear layer, BatchNorm with
//! the ReLU after it, and the two parameter updates of a TD3 step, Adam and
//! the soft update's blend. Each is the same function as Burn's (the tests
//! check them against Burn), in fewer passes over memory. On other devices
//! (wgpu, cuda) every entry point runs Burn's operations, or must not be
//! called ([`is_cpu_backend`] says which).
//!
//! # The factored-gradient contract
//!
//! The linear kernel registers its weight's gradient `dW = xᵀ · dy` not as
//! the `[inputs, outputs]` matrix (168 MB at 320 × 256) but as its factors,
//! a `[batch + 1, inputs + outputs]` tensor ([`linear`]'s module doc says
//! how). Burn passes it on as the weight's gradient, so whatever reads the
//! gradients of a network run on the CPU backend must read the factors:
//! - the only reader is [`adam`], the optimiser the learner builds here; it
//!   expands the factors a few rows at a time beside the rows it updates;
//! - a gradient whose shape is neither the weight's nor its factors' (two
//!   uses of one layer, summed by Burn) stops the step with a message that
//!   says so, never a wrong update;
//! - nothing outside this module can interpret the factors: the type that
//!   reads them is private to it. Anything else that would read gradients
//!   (Burn's own optimisers, clipping, a gradient-norm log) belongs here,
//!   beside `adam`, or must run on another backend.

mod conv;
mod linear;
mod norm;
mod updates;

pub use conv::conv2d;
pub use linear::linear;
pub use norm::{batch_norm_relu_inference, batch_norm_relu_training};
pub use updates::{FusedAdam, blend};

use burn::backend::DispatchDevice;
use burn::optim::ModuleOptimizer;
use burn::tensor::{Bytes, DType, Shape};
use burn_flex::{FlexTensor, Layout};

/// Whether `device` is Burn's CPU backend (flex), with or without autodiff:
/// where these kernels run.
pub fn is_cpu_backend(device: &burn::tensor::Device) -> bool {
    matches!(
        device.clone().inner().as_dispatch(),
        DispatchDevice::Flex(_)
    )
}

/// Adam with Burn's formula and state, β₁ 0.9, β₂ 0.999 and `epsilon`:
/// fused on the CPU backend, where it reads the linear kernel's factored
/// gradients; Burn's Adam elsewhere. The optimiser for any network these
/// kernels run.
pub fn adam(epsilon: f32) -> ModuleOptimizer {
    ModuleOptimizer::from(FusedAdam::new(epsilon))
}

/// A contiguous f32 tensor of `shape` holding `values`.
fn tensor(values: Vec<f32>, shape: impl Into<Shape>) -> FlexTensor {
    FlexTensor::new(
        Bytes::from_elems(values),
        Layout::contiguous(shape.into()),
        DType::F32,
    )
}
