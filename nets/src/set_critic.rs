//! The action-value network that reads sphere centres.

use crate::architecture::ActionJoin;
use crate::head::{Head, HeadConfig};
use crate::set_encoder::{SetEncoder, SetEncoderConfig};
use crate::spheres::SetBatch;
use burn::config::Config;
use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::{Device, Tensor};

/// Sphere set, target vector and action in, Q value out.
#[derive(Module, Debug)]
pub struct SetCritic {
    encoder: SetEncoder,
    /// The action's term in each sphere's first layer, with
    /// [`ActionJoin::PerSphere`].
    per_sphere: Option<Linear>,
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
    /// Where the action joins.
    #[config(default = "ActionJoin::Pooled")]
    pub action_join: ActionJoin,
    /// LayerNorm in the layers after pooling.
    #[config(default = false)]
    pub layer_norm: bool,
}

impl SetCriticConfig {
    /// A critic with freshly initialised weights on `device`.
    pub fn init(&self, device: &Device) -> SetCritic {
        SetCritic {
            encoder: self.encoder.init(device),
            per_sphere: (self.action_join == ActionJoin::PerSphere).then(|| {
                // The first layer's bias is the encoder's.
                LinearConfig::new(2, self.encoder.hidden)
                    .with_bias(false)
                    .init(device)
            }),
            head: HeadConfig::new(self.encoder.features() + 4, 1)
                .with_hidden(self.hidden)
                .with_layer_norm(self.layer_norm)
                .init(device),
        }
    }
}

/// What the critic computes of a set before it sees the action.
#[derive(Clone, Debug)]
#[expect(
    clippy::large_enum_variant,
    reason = "made and moved once per pass: a box would only add an allocation"
)]
pub enum SetFeatures {
    /// The pooled features, `[batch, features]`.
    Pooled(Tensor<2>),
    /// Each sphere's first-layer map, the action not yet joined (the rows
    /// of a [`SetBatch`] of `[spheres, hidden]`).
    PerSphere(SetBatch),
}

impl SetFeatures {
    /// The same features cut from the autodiff graph.
    pub fn detach(self) -> Self {
        match self {
            Self::Pooled(x) => Self::Pooled(x.detach()),
            Self::PerSphere(set) => {
                let spheres = set.spheres.clone().detach();
                Self::PerSphere(set.with_spheres(spheres))
            }
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

    /// What [`Self::forward`] computes first, and what does not depend on
    /// the action.
    pub fn encode(&self, set: SetBatch) -> SetFeatures {
        match self.per_sphere {
            None => SetFeatures::Pooled(self.encoder.forward(set)),
            Some(_) => {
                let first = self.encoder.first_layer(set.spheres.clone());
                SetFeatures::PerSphere(set.with_spheres(first))
            }
        }
    }

    /// Q from the set's features, target vector and action.
    pub fn forward_features(
        &self,
        features: SetFeatures,
        vector: Tensor<2>,
        action: Tensor<2>,
    ) -> Tensor<2> {
        let pooled = match (features, &self.per_sphere) {
            (SetFeatures::Pooled(pooled), None) => pooled,
            (SetFeatures::PerSphere(first), Some(join)) => {
                // The action's term, one row per set, and a zero row for
                // the filler of a batch without spheres.
                let term = join.forward(action.clone()); // [batch, hidden]
                let [_, hidden] = term.dims();
                let zero = Tensor::<2>::zeros([1, hidden], &term.device());
                let term = Tensor::cat(vec![term, zero], 0).select(0, first.owners.clone()); // [spheres, hidden]
                let joined = first.spheres.clone() + term;
                self.encoder.from_first_layer(first.with_spheres(joined)) // [batch, features]
            }
            _ => unreachable!("a critic's features are of its own kind"),
        };
        let x = Tensor::cat(vec![pooled, vector, action], 1); // [batch, features + 4]
        self.head.forward(x) // [batch, 1]
    }
}
