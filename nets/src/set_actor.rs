//! The policy network that reads sphere centres: the set encoder, the
//! target vector joined after pooling, and the same head as the CNN actor;
//! in the goal frame it acts along and across the heading to the target.

use crate::architecture::Frame;
use crate::goal_frame::{rows_from_goal, rows_to_goal};
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
    #[module(skip)]
    frame: Frame,
}

/// The set actor's shape.
#[derive(Config, Debug)]
pub struct SetActorConfig {
    /// The set encoder.
    pub encoder: SetEncoderConfig,
    /// Width of the two hidden layers after pooling.
    #[config(default = 64)]
    pub hidden: usize,
    /// The frame it reads and acts in.
    #[config(default = "Frame::Stage")]
    pub frame: Frame,
}

impl SetActorConfig {
    /// An actor with freshly initialised weights on `device`.
    pub fn init(&self, device: &Device) -> SetActor {
        SetActor {
            encoder: self.encoder.init(device),
            head: HeadConfig::new(self.encoder.features() + 2, 2)
                .with_hidden(self.hidden)
                .init(device),
            frame: self.frame,
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
        let heading = set.heading.clone();
        let vector = match self.frame {
            Frame::Stage => vector,
            Frame::Goal => rows_to_goal(vector, heading.clone()),
        };
        let x = self.encoder.forward(set); // [batch, features]
        let x = Tensor::cat(vec![x, vector], 1); // [batch, features + 2]
        let action = tanh(self.head.forward(x)); // [batch, 2]
        match self.frame {
            Frame::Stage => action,
            // Turned back to the stage's axes, from a box wide enough to
            // reach every corner of the stage's [-1, 1]² at any heading,
            // and shrunk back into it along its own direction: a clamp
            // would pass no gradient where both components overshoot, as
            // running flat out along a diagonal does.
            Frame::Goal => {
                let action = rows_from_goal(action * std::f32::consts::SQRT_2, heading);
                let overshoot = action.clone().abs().max_dim(1).clamp_min(1.0); // [batch, 1]
                action / overshoot
            }
        }
    }
}
