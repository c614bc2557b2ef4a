//! The permutation-invariant encoder of a sphere set: a shared per-sphere
//! MLP, then masked max and mean pooling. Per-sphere features pass ReLU
//! last, so they are never negative: padding (zeroed by the mask) can
//! neither win the max nor, divided out, move the mean, and an empty set
//! encodes as zeros.

use burn::config::Config;
use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

use crate::spheres::{SPHERE_FEATURES, SetBatch};

/// Per-sphere MLP and pooling.
#[derive(Module, Debug)]
pub struct SetEncoder {
    fc1: Linear,
    fc2: Linear,
}

/// The set encoder's shape.
#[derive(Config, Debug)]
pub struct SetEncoderConfig {
    /// Width of the per-sphere layers; the encoding is twice this (max and
    /// mean).
    #[config(default = 64)]
    pub hidden: usize,
}

impl SetEncoderConfig {
    /// An encoder with freshly initialised weights on `device`.
    pub fn init(&self, device: &Device) -> SetEncoder {
        SetEncoder {
            fc1: LinearConfig::new(SPHERE_FEATURES, self.hidden).init(device),
            fc2: LinearConfig::new(self.hidden, self.hidden).init(device),
        }
    }

    /// Width of the encoding.
    pub fn features(&self) -> usize {
        2 * self.hidden
    }
}

impl SetEncoder {
    /// # Shapes
    /// - `set.spheres`: `[batch, n, 3]`, `set.mask`: `[batch, n, 1]`
    /// - output: `[batch, 2 * hidden]` (max, then mean)
    pub fn forward(&self, set: SetBatch) -> Tensor<2> {
        let [batch, n, features] = set.spheres.dims();
        // One matrix product over every sphere of the batch.
        let x = set.spheres.reshape([batch * n, features]); // [batch n, 3]
        let x = relu(self.fc1.forward(x)); // [batch n, hidden]
        let x = relu(self.fc2.forward(x)); // [batch n, hidden]
        let hidden = x.dims()[1];
        let x = x.reshape([batch, n, hidden]) * set.mask.clone(); // [batch, n, hidden]
        let count = set.mask.sum_dim(1).clamp_min(1.0); // [batch, 1, 1]
        let max = x.clone().max_dim(1); // [batch, 1, hidden]
        let mean = x.sum_dim(1) / count; // [batch, 1, hidden]
        Tensor::cat(vec![max, mean], 2).reshape([batch, 2 * hidden]) // [batch, 2 * hidden]
    }
}
