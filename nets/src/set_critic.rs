//! The action-value network that reads sphere centres.

use crate::approach::{PASSING_FEATURES, passing};
use crate::architecture::{ActionJoin, Frame};
use crate::goal_frame::rows_to_goal;
use crate::head::{Head, HeadConfig};
use crate::set_encoder::{SetEncoder, SetEncoderConfig};
use crate::spheres::{SetBatch, rows_or_zero};
use burn::config::Config;
use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::{Device, Tensor};

/// Sphere set, target vector and action in, Q value out.
#[derive(Module, Debug)]
pub struct SetCritic {
    encoder: SetEncoder,
    /// The action's term in each sphere's first layer, with
    /// [`ActionJoin::PerSphere`] or [`ActionJoin::Approach`].
    per_sphere: Option<Linear>,
    /// The term of where the action passes each sphere, with
    /// [`ActionJoin::Approach`].
    approach: Option<Linear>,
    head: Head,
    #[module(skip)]
    frame: Frame,
}

/// The set critic's shape.
#[derive(Config, Debug)]
pub struct SetCriticConfig {
    /// The set encoder.
    pub encoder: SetEncoderConfig,
    /// Width of the two hidden layers after pooling.
    #[config(default = 64)]
    pub hidden: usize,
    /// Where the action joins.
    #[config(default = "ActionJoin::Pooled")]
    pub action_join: ActionJoin,
    /// LayerNorm in the layers after pooling.
    #[config(default = false)]
    pub layer_norm: bool,
    /// The frame it reads the scene and the action in.
    #[config(default = "Frame::Stage")]
    pub frame: Frame,
}

impl SetCriticConfig {
    /// A critic with freshly initialised weights on `device`.
    pub fn init(&self, device: &Device) -> SetCritic {
        SetCritic {
            encoder: self.encoder.init(device),
            // The first layer's bias is the encoder's.
            per_sphere: (self.action_join != ActionJoin::Pooled).then(|| {
                LinearConfig::new(2, self.encoder.hidden)
                    .with_bias(false)
                    .init(device)
            }),
            approach: (self.action_join == ActionJoin::Approach).then(|| {
                LinearConfig::new(PASSING_FEATURES, self.encoder.hidden)
                    .with_bias(false)
                    .init(device)
            }),
            head: HeadConfig::new(self.encoder.features() + 4, 1)
                .with_hidden(self.hidden)
                .with_layer_norm(self.layer_norm)
                .init(device),
            frame: self.frame,
        }
    }
}

/// What the critic computes of a set before it sees the action, and the
/// heading that turns the vector and the action into the goal frame.
#[derive(Clone, Debug)]
pub struct SetFeatures {
    seen: Seen,
    heading: Tensor<2>,
}

#[derive(Clone, Debug)]
#[expect(
    clippy::large_enum_variant,
    reason = "made and moved once per pass: a box would only add an allocation"
)]
enum Seen {
    /// The pooled features, `[batch, features]`.
    Pooled(Tensor<2>),
    /// Each sphere's first-layer map, the action not yet joined (the rows
    /// of a [`SetBatch`] of `[spheres, hidden]`), and with
    /// [`ActionJoin::Approach`] each sphere's offset, `[spheres, 2]`.
    PerSphere(SetBatch, Option<Tensor<2>>),
}

impl SetFeatures {
    /// The same features cut from the autodiff graph.
    pub fn detach(self) -> Self {
        let seen = match self.seen {
            Seen::Pooled(x) => Seen::Pooled(x.detach()),
            Seen::PerSphere(set, offsets) => {
                Seen::PerSphere(set.map_spheres(Tensor::detach), offsets.map(Tensor::detach))
            }
        };
        Self { seen, ..self }
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

    /// What [`Self::forward`] computes first, and what does not depend on
    /// the action.
    pub fn encode(&self, set: SetBatch) -> SetFeatures {
        let heading = set.heading.clone();
        let seen = match self.per_sphere {
            None => Seen::Pooled(self.encoder.forward(set)),
            Some(_) => {
                let offsets = self.approach.as_ref().map(|_| set.offsets());
                let first = set.map_spheres(|spheres| self.encoder.first_layer(spheres));
                Seen::PerSphere(first, offsets)
            }
        };
        SetFeatures { seen, heading }
    }

    /// Q from the set's features, target vector and action.
    pub fn forward_features(
        &self,
        features: SetFeatures,
        vector: Tensor<2>,
        action: Tensor<2>,
    ) -> Tensor<2> {
        let (vector, action) = match self.frame {
            Frame::Stage => (vector, action),
            Frame::Goal => (
                rows_to_goal(vector, features.heading.clone()),
                rows_to_goal(action, features.heading),
            ),
        };
        let pooled = match (features.seen, &self.per_sphere) {
            (Seen::Pooled(pooled), None) => pooled,
            (Seen::PerSphere(first, offsets), Some(join)) => {
                // The action's term, one row per set, gathered to its
                // spheres (zeros for the filler of a batch without any).
                let mut term = rows_or_zero(join.forward(action.clone()), first.owners.clone()); // [spheres, hidden]
                if let (Some(offsets), Some(approach)) = (offsets, &self.approach) {
                    let actions = rows_or_zero(action.clone(), first.owners.clone()); // [spheres, 2]
                    term = term + approach.forward(passing(offsets, actions)); // [spheres, hidden]
                }
                self.encoder
                    .from_first_layer(first.map_spheres(|spheres| spheres + term)) // [batch, features]
            }
            _ => unreachable!("a critic's features are of its own kind"),
        };
        let x = Tensor::cat(vec![pooled, vector, action], 1); // [batch, features + 4]
        self.head.forward(x) // [batch, 1]
    }
}
