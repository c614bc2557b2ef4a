//! The permutation-invariant encoder of a sphere set: a shared per-sphere
//! MLP on the batch's real spheres, then pooling over each set (max and
//! mean, or either alone). Per-sphere features pass ReLU last, so they are
//! never negative: padding (zeros) can neither win the max nor move the
//! sum the mean divides by the set's size, and an empty set encodes as
//! zeros.

use crate::architecture::{Pooling, SphereInputs};
use crate::spheres::{SetBatch, rows_or_zero};
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
    /// What each sphere's row holds.
    #[config(default = "SphereInputs::Positions")]
    pub inputs: SphereInputs,
}

impl SetEncoderConfig {
    /// An encoder with freshly initialised weights on `device`.
    pub fn init(&self, device: &Device) -> SetEncoder {
        SetEncoder {
            fc1: LinearConfig::new(self.inputs.features(), self.hidden).init(device),
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
    /// - `set`: see [`SetBatch`]: `[spheres, features]` packed, `batch`
    ///   sets of up to `width`
    /// - output: `[batch, hidden]`, or `[batch, 2 * hidden]` for max and
    ///   mean (max first)
    pub fn forward(&self, set: SetBatch) -> Tensor<2> {
        self.from_first_layer(set.map_spheres(|spheres| self.first_layer(spheres)))
    }

    /// The first layer's affine map of each sphere (`[spheres, hidden]`),
    /// before its ReLU: where a per-set term can join each sphere.
    pub fn first_layer(&self, spheres: Tensor<2>) -> Tensor<2> {
        self.fc1.forward(spheres)
    }

    /// The rest of [`Self::forward`] from `first`, whose rows are
    /// [`Self::first_layer`]'s (plus anything joined): ReLU, the second
    /// layer, pooling.
    pub fn from_first_layer(&self, first: SetBatch) -> Tensor<2> {
        let (batch, width) = (first.len(), first.width);
        // The MLP on real spheres only, one matrix product per layer.
        let x = relu(first.spheres); // [spheres, hidden]
        let x = relu(self.fc2.forward(x)); // [spheres, hidden]
        let [_, hidden] = x.dims();
        // Padding reads a zero row: never above a ReLU output, nothing
        // added to a sum.
        let x = rows_or_zero(x, first.slots) // [batch width, hidden]
            .reshape([batch, width, hidden]); // [batch, width, hidden]
        let mean = || x.clone().sum_dim(1).reshape([batch, hidden]) / first.counts.clone(); // [batch, hidden]
        let max = || x.clone().max_dim(1).reshape([batch, hidden]); // [batch, hidden]
        match self.pooling {
            Pooling::MaxMean => Tensor::cat(vec![max(), mean()], 1), // [batch, 2 hidden]
            Pooling::Max => max(),
            Pooling::Mean => mean(),
        }
    }
}
