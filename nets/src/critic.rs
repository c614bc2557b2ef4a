//! The action-value network.

use crate::encoder::{Encoder, EncoderConfig};
use burn::config::Config;
use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

/// Image, target vector and action in, Q value out.
#[derive(Module, Debug)]
pub struct Critic {
    encoder: Encoder,
    fc1: Linear,
    fc2: Linear,
    out: Linear,
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
        let features = self.encoder.features;
        Critic {
            encoder: self.encoder.init(device),
            fc1: LinearConfig::new(features + 4, self.hidden).init(device),
            fc2: LinearConfig::new(self.hidden, self.hidden).init(device),
            out: LinearConfig::new(self.hidden, 1).init(device),
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
        let x = relu(self.fc1.forward(x)); // [batch, 64]
        let x = relu(self.fc2.forward(x)); // [batch, 64]
        self.out.forward(x) // [batch, 1]
    }
}
