//! The action-value network.

use crate::encoder::{Encoder, EncoderConfig};
use crate::head::{Head, HeadConfig};
use burn::config::Config;
use burn::module::Module;
use burn::tensor::{Device, Tensor};

/// Image, target vector and action in, Q value out.
#[derive(Module, Debug)]
pub struct Critic {
    encoder: Encoder,
    head: Head,
}

/// The critic's shape.
#[derive(Config, Debug)]
pub struct CriticConfig {
    /// The image encoder.
    pub encoder: EncoderConfig,
    /// Width of the two hidden layers after the encoder.
    #[config(default = 64)]
    pub hidden: usize,
}

impl CriticConfig {
    /// A critic with freshly initialised weights on `device`.
    pub fn init(&self, device: &Device) -> Critic {
        Critic {
            encoder: self.encoder.init(device),
            head: HeadConfig::new(self.encoder.features + 4, 1)
                .with_hidden(self.hidden)
                .init(device),
        }
    }
}

impl Critic {
    /// Estimates Q(observation, action).
    ///
    /// # Shapes
    /// - `image`: `[batch, 1, height, width]`
    /// - `vector`: `[batch, 2]`
    /// - `action`: `[batch, 2]`
    /// - output: `[batch, 1]`
    pub fn forward(&self, image: Tensor<4>, vector: Tensor<2>, action: Tensor<2>) -> Tensor<2> {
        self.forward_features(self.encode(image), vector, action)
    }

    /// The image features (`[batch, 512]`): what [`Self::forward`] computes
    /// first, and what does not depend on the action.
    pub fn encode(&self, image: Tensor<4>) -> Tensor<2> {
        self.encoder.forward(image)
    }

    /// Q from image features, target vector and action.
    pub fn forward_features(
        &self,
        features: Tensor<2>,
        vector: Tensor<2>,
        action: Tensor<2>,
    ) -> Tensor<2> {
        let x = Tensor::cat(vec![features, vector, action], 1); // [batch, 516]
        self.head.forward(x) // [batch, 1]
    }
}
