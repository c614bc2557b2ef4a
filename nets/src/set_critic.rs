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
    /// Action units per unit of a row's motion columns, where the rows
    /// carry motion: the trap then passes each sphere as it moves relative
    /// to it.
    #[module(skip)]
    motion_in_actions: Option<f32>,
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
    /// Action units per unit of the rows' motion columns, where they have
    /// them: with [`ActionJoin::Approach`], each sphere is passed as the
    /// trap moves relative to it.
    #[config(default = "None")]
    pub motion_in_actions: Option<f32>,
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
            motion_in_actions: self.motion_in_actions,
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
    /// [`ActionJoin::Approach`] what the action passes.
    PerSphere(SetBatch, Option<Passed>),
}

/// What an action passes: each sphere's offset and, where the rows carry
/// motion, its velocity in action units; `[spheres, 2]` each.
#[derive(Clone, Debug)]
struct Passed {
    offsets: Tensor<2>,
    velocities: Option<Tensor<2>>,
}

impl Passed {
    /// What was seen of `set`'s spheres; their velocities where the rows
    /// carry motion, at `motion_in_actions` action units per unit.
    fn of(set: &SetBatch, motion_in_actions: Option<f32>) -> Self {
        Self {
            offsets: set.offsets(),
            velocities: motion_in_actions.map(|k| set.motions() * k),
        }
    }

    /// [`passing`] of each sphere by the trap moving at `actions` (one row
    /// per sphere) relative to it.
    fn passing(self, actions: Tensor<2>) -> Tensor<2> {
        let relative = match self.velocities {
            Some(v) => actions - v,
            None => actions,
        };
        passing(self.offsets, relative)
    }

    fn detach(self) -> Self {
        Self {
            offsets: self.offsets.detach(),
            velocities: self.velocities.map(Tensor::detach),
        }
    }
}

impl SetFeatures {
    /// The same features cut from the autodiff graph.
    pub fn detach(self) -> Self {
        let seen = match self.seen {
            Seen::Pooled(x) => Seen::Pooled(x.detach()),
            Seen::PerSphere(set, passed) => {
                Seen::PerSphere(set.map_spheres(Tensor::detach), passed.map(Passed::detach))
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
                let passed = self
                    .approach
                    .as_ref()
                    .map(|_| Passed::of(&set, self.motion_in_actions));
                let first = set.map_spheres(|spheres| self.encoder.first_layer(spheres));
                Seen::PerSphere(first, passed)
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
            (Seen::PerSphere(first, passed), Some(join)) => {
                // Each set's action gathered to its spheres (zeros for the
                // filler of a batch without any), and its term.
                let actions = rows_or_zero(action.clone(), first.owners.clone()); // [spheres, 2]
                let mut term = join.forward(actions.clone()); // [spheres, hidden]
                if let (Some(passed), Some(approach)) = (passed, &self.approach) {
                    term = term + approach.forward(passed.passing(actions)); // [spheres, hidden]
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::architecture::{SetShape, SphereInputs};
    use crate::spheres::{Scene, SphereSets};
    use burn::tensor::TensorData;

    /// A sphere 64 px right of the trap and 16 px below, moving `moved` px
    /// since the last step, passed by a trap driven at `action`; stage
    /// speed 10 px per unit of action.
    fn passed(moved: [f32; 2], action: [f32; 2]) -> Vec<f32> {
        let shape = SetShape {
            inputs: SphereInputs::Motion,
            ..SetShape::new([320, 256])
        };
        let sets = SphereSets::new(&shape, [320, 256]);
        let device = Device::flex();
        let centres = [[160.0 + 64.0, 128.0 + 16.0]];
        let displacements = [Some(moved)];
        let scene = Scene::new(&centres, &displacements, [1.0, 0.0]);
        let set = sets.batch([scene].into_iter(), &device);
        let actions = Tensor::from_data(TensorData::new(action.to_vec(), [1, 2]), &device);
        Passed::of(&set, Some(shape.motion_unit_px / 10.0))
            .passing(actions)
            .into_data()
            .try_to_vec::<f32>()
            .unwrap()
    }

    #[test]
    fn a_sphere_is_passed_as_the_trap_moves_relative_to_it() {
        // Moving with the trap, it is never approached: as at rest.
        assert_eq!(passed([5.0, 2.0], [0.5, 0.2]), passed([0.0; 2], [0.0; 2]));
        // Coming at a trap at rest is passing it at the same speed.
        let head_on = passed([-2.0, 0.0], [0.0, 0.0]);
        let driven = passed([0.0, 0.0], [0.2, 0.0]);
        for (a, b) in head_on.iter().zip(&driven) {
            assert!((a - b).abs() < 1e-6, "{head_on:?} against {driven:?}");
        }
        // Below the trap's line and drifting down 2 px a step while the
        // trap drives right at 10: missed by 28 px, not 16 (within the
        // speed floor's shrink). Offsets are in units of 160 px here.
        let miss = |features: &[f32]| features[2] * 160.0 / 8.0;
        let straight = passed([0.0, 0.0], [1.0, 0.0]);
        let drifting = passed([0.0, 2.0], [1.0, 0.0]);
        assert!((miss(&straight) - 16.0).abs() < 0.5, "{straight:?}");
        assert!((miss(&drifting) - 28.2).abs() < 0.5, "{drifting:?}");
    }
}
