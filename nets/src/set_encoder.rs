//! The permutation-invariant encoder of a sphere set: a shared per-sphere
//! MLP, then masked pooling (max and mean, or either alone). Per-sphere
//! features pass ReLU last, so they are never negative: padding (zeroed by
//! the mask) can neither win the max nor, divided out, move the mean, and
//! an empty set encodes as zeros.

use crate::architecture::Pooling;
use crate::spheres::{SPHERE_FEATURES, SetBatch};
use burn::config::Config;
use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

/// Per-sphere MLP and pooling.
#[derive(Module, Debug)]
pub struct SetEncoder {
    fc1: Linear,
    fc2: Linear,
    #[module(skip)]
    pooling: Pooling,
}

/// The set encoder's shape.
#[derive(Config, Debug)]
pub struct SetEncoderConfig {
    /// Width of the per-sphere layers.
    #[config(default = 64)]
    pub hidden: usize,
    /// How the per-sphere features are pooled.
    #[config(default = "Pooling::MaxMean")]
    pub pooling: Pooling,
}

impl SetEncoderConfig {
    /// An encoder with freshly initialised weights on `device`.
    pub fn init(&self, device: &Device) -> SetEncoder {
        SetEncoder {
            fc1: LinearConfig::new(SPHERE_FEATURES, self.hidden).init(device),
            fc2: LinearConfig::new(self.hidden, self.hidden).init(device),
            pooling: self.pooling,
        }
    }

    /// Width of the encoding.
    pub fn features(&self) -> usize {
        self.pooling.factor() * self.hidden
    }
}

impl SetEncoder {
    /// # Shapes
    /// - `set.spheres`: `[batch, n, 3]`, `set.mask`: `[batch, n, 1]`
    /// - output: `[batch, hidden]`, or `[batch, 2 * hidden]` for max and
    ///   mean (max first)
    pub fn forward(&self, set: SetBatch) -> Tensor<2> {
        let [batch, n, features] = set.spheres.dims();
        // One matrix product over every sphere of the batch.
        let x = set.spheres.reshape([batch * n, features]); // [batch n, 3]
        let x = relu(self.fc1.forward(x)); // [batch n, hidden]
        let x = relu(self.fc2.forward(x)); // [batch n, hidden]
        let hidden = x.dims()[1];
        let x = x.reshape([batch, n, hidden]) * set.mask.clone(); // [batch, n, hidden]
        let mean = || {
            let count = set.mask.clone().sum_dim(1).clamp_min(1.0); // [batch, 1, 1]
            x.clone().sum_dim(1) / count // [batch, 1, hidden]
        };
        let pooled = match self.pooling {
            Pooling::MaxMean => Tensor::cat(vec![x.clone().max_dim(1), mean()], 2),
            Pooling::Max => x.clone().max_dim(1),
            Pooling::Mean => mean(),
        }; // [batch, 1, factor * hidden]
        let width = pooled.dims()[2];
        pooled.reshape([batch, width]) // [batch, factor * hidden]
    }
}
