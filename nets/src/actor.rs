//! The policy network.

use crate::encoder::{Encoder, EncoderConfig};
use crate::head::{Head, HeadConfig};
use burn::config::Config;
use burn::module::Module;
use burn::tensor::activation::tanh;
use burn::tensor::{Device, Tensor};

/// Image and target vector in, stage velocities in [-1, 1]² out.
#[derive(Module, Debug)]
pub struct Actor {
    encoder: Encoder,
    head: Head,
}

/// The actor's shape.
#[derive(Config, Debug)]
pub struct ActorConfig {
    /// The image encoder.
    pub encoder: EncoderConfig,
    /// Width of the two hidden layers after the encoder.
    #[config(default = 64)]
    pub hidden: usize,
}

impl ActorConfig {
    /// An actor with freshly initialised weights on `device`.
    pub fn init(&self, device: &Device) -> Actor {
        Actor {
            encoder: self.encoder.init(device),
            head: HeadConfig::new(self.encoder.features + 2, 2)
                .with_hidden(self.hidden)
                .init(device),
        }
    }
}

impl Actor {
    /// Chooses actions.
    ///
    /// # Shapes
    /// - `image`: `[batch, 1, height, width]`
    /// - `vector`: `[batch, 2]`
    /// - output: `[batch, 2]`, each component in [-1, 1]
    pub fn forward(&self, image: Tensor<4>, vector: Tensor<2>) -> Tensor<2> {
        let x = self.encoder.forward(image); // [batch, 512]
        let x = Tensor::cat(vec![x, vector], 1); // [batch, 514]
        tanh(self.head.forward(x)) // [batch, 2]
    }
}
