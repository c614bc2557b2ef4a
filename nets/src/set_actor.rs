//! The policy network that reads sphere centres: the set encoder, the
//! target vector joined after pooling, and the same head as the CNN actor.

use crate::head::{Head, HeadConfig};
use crate::set_encoder::{SetEncoder, SetEncoderConfig};
use crate::spheres::SetBatch;
use burn::config::Config;
use burn::module::Module;
use burn::tensor::activation::tanh;
use burn::tensor::{Device, Tensor};

/// Sphere set and target vector in, stage velocities in [-1, 1]² out.
#[derive(Module, Debug)]
pub struct SetActor {
    encoder: SetEncoder,
    head: Head,
}

/// The set actor's shape.
#[derive(Config, Debug)]
pub struct SetActorConfig {
    /// The set encoder.
    pub encoder: SetEncoderConfig,
    /// Width of the two hidden layers after pooling.
    #[config(default = 64)]
    pub hidden: usize,
}

impl SetActorConfig {
    /// An actor with freshly initialised weights on `device`.
    pub fn init(&self, device: &Device) -> SetActor {
        SetActor {
            encoder: self.encoder.init(device),
            head: HeadConfig::new(self.encoder.features() + 2, 2)
                .with_hidden(self.hidden)
                .init(device),
        }
    }
}

impl SetActor {
    /// Chooses actions.
    ///
    /// # Shapes
    /// - `set`: see [`crate::SetBatch`]
    /// - `vector`: `[batch, 2]`
    /// - output: `[batch, 2]`, each component in [-1, 1]
    pub fn forward(&self, set: SetBatch, vector: Tensor<2>) -> Tensor<2> {
        let x = self.encoder.forward(set); // [batch, features]
        let x = Tensor::cat(vec![x, vector], 1); // [batch, features + 2]
        tanh(self.head.forward(x)) // [batch, 2]
    }
}
