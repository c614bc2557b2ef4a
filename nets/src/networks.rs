//! What training and inference need of an architecture, whichever it is:
//! fresh networks, the input tensors of a batch of observations, and the
//! forward passes. TD3 and the policies are written once against
//! [`Networks`]; [`PaperNetworks`] and [`SetNetworks`] implement it.

use crate::actor::{Actor, ActorConfig};
use crate::architecture::{Architecture, SetShape};
use crate::critic::{Critic, CriticConfig};
use crate::encoder::EncoderConfig;
use crate::images::render_images;
use crate::set_actor::{SetActor, SetActorConfig};
use crate::set_critic::{SetCritic, SetCriticConfig, SetFeatures};
use crate::set_encoder::SetEncoderConfig;
use crate::spheres::{Scene, SetBatch, SphereSets};
use burn::module::{Module, ModuleDisplay};
use burn::tensor::{Device, Tensor};
use tweezer_config::ConfigError;
use tweezer_gym::{EnvConfig, Renderer};

/// An architecture's networks and how observations become their inputs.
pub trait Networks: Clone + Send + Sync + 'static {
    /// What the networks read of a batch of observations besides the
    /// target vector.
    type Input: Clone + Send + Sync;
    /// The policy network.
    type Actor: Module + ModuleDisplay;
    /// The action-value network.
    type Critic: Module + ModuleDisplay;
    /// What the critic computes of an input before it sees the vector and
    /// the action.
    type Features: Clone + Send + Sync;

    /// The architecture, as snapshots and checkpoints record it.
    fn architecture(&self) -> Architecture;

    /// A fresh actor on `device`.
    fn actor(&self, device: &Device) -> Self::Actor;

    /// A fresh critic on `device`.
    fn critic(&self, device: &Device) -> Self::Critic;

    /// The input of each observation's scene, as one batch.
    fn input<'a>(
        &self,
        scenes: impl ExactSizeIterator<Item = Scene<'a>>,
        device: &Device,
    ) -> Self::Input;

    /// `input` on a device without autodiff.
    fn valid(input: Self::Input) -> Self::Input;

    /// Actions, `[batch, 2]` in [-1, 1].
    fn act(actor: &Self::Actor, input: Self::Input, vector: Tensor<2>) -> Tensor<2>;

    /// The critic's features of `input`: what does not depend on the
    /// vector or the action.
    fn features(critic: &Self::Critic, input: Self::Input) -> Self::Features;

    /// `features` cut from the autodiff graph.
    fn detach(features: Self::Features) -> Self::Features;

    /// Q, `[batch, 1]`, from the critic's features.
    fn value(
        critic: &Self::Critic,
        features: Self::Features,
        vector: Tensor<2>,
        action: Tensor<2>,
    ) -> Tensor<2>;
}

/// An architecture's networks, chosen at run time: code generic over
/// [`Networks`] runs on whichever it holds through [`with_networks!`].
#[derive(Clone, Debug)]
pub enum AnyNetworks {
    /// The paper's CNNs.
    Paper(PaperNetworks),
    /// The set networks.
    Set(SetNetworks),
}

/// Evaluates `$body` with `$networks` bound to the concrete networks an
/// [`AnyNetworks`] holds, compiled once for each architecture:
/// `with_networks!(any, |networks| Trainer::new(networks, ...))`.
#[macro_export]
macro_rules! with_networks {
    ($any:expr, |$networks:ident| $body:expr) => {
        match $any {
            $crate::AnyNetworks::Paper($networks) => $body,
            $crate::AnyNetworks::Set($networks) => $body,
        }
    };
}

impl Architecture {
    /// This architecture's networks acting in `env`: a CNN on the images
    /// `env` renders (a snapshot of another resolution is then refused by
    /// [`crate::decode`]), a set network on `env`'s field of view at the
    /// scale it was trained at.
    pub fn networks(&self, env: &EnvConfig) -> Result<AnyNetworks, ConfigError> {
        Ok(match *self {
            Self::Paper { .. } => {
                AnyNetworks::Paper(PaperNetworks::new(Renderer::for_config(env)?))
            }
            Self::Set(shape) => AnyNetworks::Set(SetNetworks::for_env(shape, env)),
        })
    }
}

/// The paper's CNNs on images of the renderer's resolution.
#[derive(Clone, Debug)]
pub struct PaperNetworks {
    renderer: Renderer,
}

impl PaperNetworks {
    /// CNNs for the images `renderer` draws.
    pub fn new(renderer: Renderer) -> Self {
        Self { renderer }
    }

    fn encoder(&self) -> EncoderConfig {
        EncoderConfig::new(self.renderer.height(), self.renderer.width())
    }
}

impl Networks for PaperNetworks {
    type Input = Tensor<4>;
    type Actor = Actor;
    type Critic = Critic;
    type Features = Tensor<2>;

    fn architecture(&self) -> Architecture {
        Architecture::Paper {
            height: self.renderer.height(),
            width: self.renderer.width(),
        }
    }

    fn actor(&self, device: &Device) -> Actor {
        ActorConfig::new(self.encoder()).init(device)
    }

    fn critic(&self, device: &Device) -> Critic {
        CriticConfig::new(self.encoder()).init(device)
    }

    /// Images show where the spheres are, not how they move.
    fn input<'a>(
        &self,
        scenes: impl ExactSizeIterator<Item = Scene<'a>>,
        device: &Device,
    ) -> Tensor<4> {
        render_images(&self.renderer, scenes.map(|s| s.centres), device)
    }

    fn valid(input: Tensor<4>) -> Tensor<4> {
        input.valid()
    }

    fn act(actor: &Actor, input: Tensor<4>, vector: Tensor<2>) -> Tensor<2> {
        actor.forward(input, vector)
    }

    fn features(critic: &Critic, input: Tensor<4>) -> Tensor<2> {
        critic.encode(input)
    }

    fn detach(features: Tensor<2>) -> Tensor<2> {
        features.detach()
    }

    fn value(
        critic: &Critic,
        features: Tensor<2>,
        vector: Tensor<2>,
        action: Tensor<2>,
    ) -> Tensor<2> {
        critic.forward_features(features, vector, action)
    }
}

/// The set networks on the sphere centres of a field of view.
#[derive(Clone, Debug)]
pub struct SetNetworks {
    shape: SetShape,
    sets: SphereSets,
    /// How far the trap moves in a step at full action, px: the critic
    /// weighs an action against each sphere's motion in these units.
    stage_speed_px: f32,
}

impl SetNetworks {
    /// Networks of `shape` seeing scenes of a `fov_px` field (which may be
    /// wider than the one `shape` was trained on: more centres, the same
    /// scale), on a stage of the default speed.
    pub fn new(shape: SetShape, fov_px: [u32; 2]) -> Self {
        Self {
            sets: SphereSets::new(&shape, fov_px),
            shape,
            stage_speed_px: EnvConfig::default().stage_speed_px as f32,
        }
    }

    /// The networks of `shape` acting in `env`: its field of view and its
    /// stage's speed.
    pub fn for_env(shape: SetShape, env: &EnvConfig) -> Self {
        Self {
            stage_speed_px: env.stage_speed_px as f32,
            ..Self::new(shape, env.fov_px)
        }
    }

    fn encoder(&self) -> SetEncoderConfig {
        SetEncoderConfig::new()
            .with_hidden(self.shape.sphere_hidden)
            .with_pooling(self.shape.pooling)
            .with_inputs(self.shape.inputs)
    }

    /// How observations become sets.
    pub fn sets(&self) -> &SphereSets {
        &self.sets
    }
}

impl Networks for SetNetworks {
    type Input = SetBatch;
    type Actor = SetActor;
    type Critic = SetCritic;
    type Features = SetFeatures;

    fn architecture(&self) -> Architecture {
        Architecture::Set(self.shape)
    }

    fn actor(&self, device: &Device) -> SetActor {
        SetActorConfig::new(self.encoder())
            .with_hidden(self.shape.head_hidden)
            .with_frame(self.shape.frame)
            .init(device)
    }

    fn critic(&self, device: &Device) -> SetCritic {
        SetCriticConfig::new(self.encoder())
            .with_hidden(self.shape.head_hidden)
            .with_action_join(self.shape.action_join)
            .with_layer_norm(self.shape.critic_layer_norm)
            .with_frame(self.shape.frame)
            .with_motion_in_actions(
                self.shape
                    .inputs
                    .has_motion()
                    .then_some(self.shape.motion_unit_px / self.stage_speed_px),
            )
            .init(device)
    }

    fn input<'a>(
        &self,
        scenes: impl ExactSizeIterator<Item = Scene<'a>>,
        device: &Device,
    ) -> SetBatch {
        self.sets.batch(scenes, device)
    }

    fn valid(input: SetBatch) -> SetBatch {
        input.valid()
    }

    fn act(actor: &SetActor, input: SetBatch, vector: Tensor<2>) -> Tensor<2> {
        actor.forward(input, vector)
    }

    fn features(critic: &SetCritic, input: SetBatch) -> SetFeatures {
        critic.encode(input)
    }

    fn detach(features: SetFeatures) -> SetFeatures {
        features.detach()
    }

    fn value(
        critic: &SetCritic,
        features: SetFeatures,
        vector: Tensor<2>,
        action: Tensor<2>,
    ) -> Tensor<2> {
        critic.forward_features(features, vector, action)
    }
}
