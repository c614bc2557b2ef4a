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
        let x = self.encoder.forward(image); // [batch, 512]
        let x = Tensor::cat(vec![x, vector, action], 1); // [batch, 516]
        self.head.forward(x) // [batch, 1]
    }
}
