//! The action-value network that reads sphere centres.

use crate::head::{Head, HeadConfig};
use crate::set_encoder::{SetEncoder, SetEncoderConfig};
use crate::spheres::SetBatch;
use burn::config::Config;
use burn::module::Module;
use burn::tensor::{Device, Tensor};

/// Sphere set, target vector and action in, Q value out.
#[derive(Module, Debug)]
pub struct SetCritic {
    encoder: SetEncoder,
    head: Head,
}

/// The set critic's shape.
#[derive(Config, Debug)]
pub struct SetCriticConfig {
    /// The set encoder.
    pub encoder: SetEncoderConfig,
    /// Width of the two hidden layers after pooling.
    #[config(default = 64)]
    pub hidden: usize,
}

impl SetCriticConfig {
    /// A critic with freshly initialised weights on `device`.
    pub fn init(&self, device: &Device) -> SetCritic {
        SetCritic {
            encoder: self.encoder.init(device),
            head: HeadConfig::new(self.encoder.features() + 4, 1)
                .with_hidden(self.hidden)
                .init(device),
        }
    }
}

impl SetCritic {
    /// Estimates Q(observation, action).
    ///
    /// # Shapes
    /// - `set`: see [`crate::SetBatch`]
    /// - `vector`: `[batch, 2]`
    /// - `action`: `[batch, 2]`
    /// - output: `[batch, 1]`
    pub fn forward(&self, set: SetBatch, vector: Tensor<2>, action: Tensor<2>) -> Tensor<2> {
        self.forward_features(self.encode(set), vector, action)
    }

    /// The pooled set features (`[batch, features]`): what
    /// [`Self::forward`] computes first, and what does not depend on the
    /// action.
    pub fn encode(&self, set: SetBatch) -> Tensor<2> {
        self.encoder.forward(set)
    }

    /// Q from pooled set features, target vector and action.
    pub fn forward_features(
        &self,
        features: Tensor<2>,
        vector: Tensor<2>,
        action: Tensor<2>,
    ) -> Tensor<2> {
        let x = Tensor::cat(vec![features, vector, action], 1); // [batch, features + 4]
        self.head.forward(x) // [batch, 1]
    }
}
