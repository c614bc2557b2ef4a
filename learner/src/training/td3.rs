//! TD3 (Fujimoto, van Hoof and Meger, 2018) for either architecture
//! ([`Networks`]), in the order of the paper's pseudo-code: target actions
//! with clipped noise, the smaller of the twin target critics, the critic
//! loss; every `policy_delay` updates the actor loss and the soft target
//! updates. Targets run without autodiff, so their
//! BatchNorm layers use running statistics. Where the passes run
//! ([`Passes`]) and how Burn modules are stepped in place
//! ([`crate::training::module_updates`]) live below the algorithm.
//!
//! Changes from the paper (`docs/spec.md`, "TD3"), each off or at the
//! paper's value by default:
//! - `reward_scale`: rewards are scaled before the TD target (the optimal
//!   policy is unchanged);
//! - `action_l2`: a penalty on the mean squared action in the actor's loss;
//! - `n_step`: the critics learn from n-step returns;
//! - `imitation`: the actor also imitates a guide's action (the planner's,
//!   labelled on arrival), as in TD3+BC (Fujimoto and Gu, 2021), with Q
//!   normalised by its mean magnitude so that the weight is scale-free;
//! - the actor's loss reads Q1's encoder features detached: they do not
//!   depend on π, so the backward pass skips Q1's encoder;
//! - Adam's epsilon is PyTorch's 1e-8, not Burn's 1e-5.
//!
//! The rest of the loop lives elsewhere: exploration noise and uniform
//! warm-up in the actors (`tweezer-actor`), uniform sampling in the replay
//! (`replay`), the update-to-data ratio in the rate limiter (`limiter`), and
//! the training thread that ties them together (`trainer`).

use crate::training::module_updates::{
    merged_gradients, scalar, settle_running_statistics, soft_update_in_place, step_in_place,
};
use crate::training::passes::Passes;
use burn::module::{Module, ModuleDisplay};
use burn::nn::loss::{MseLoss, Reduction};
use burn::optim::{GradientsParams, ModuleOptimizer, OptimizerRecord};
use burn::store::{ModuleRecord, RecordError};
use burn::tensor::{Bytes, Device, Distribution, Tensor};
use serde::{Deserialize, Serialize};
use tweezer_config::ConfigError;
use tweezer_nets::{Networks, cpu_kernels};

/// A batch of transitions as tensors, on the training device; `I` is the
/// networks' input (images or sphere sets).
#[derive(Clone, Debug)]
pub struct Minibatch<I> {
    /// What the networks read of the observations.
    pub input: I,
    /// `[batch, 2]` target vectors.
    pub vector: Tensor<2>,
    /// `[batch, 2]` actions taken.
    pub action: Tensor<2>,
    /// `[batch, 1]` rewards.
    pub reward: Tensor<2>,
    /// `[batch, 1]`: 1 where the episode terminated (no bootstrap).
    pub terminated: Tensor<2>,
    /// `[batch, 1]`: steps from the observation to the next (n-step
    /// returns; 1 otherwise): the bootstrap is discounted by γ to this.
    pub steps: Tensor<2>,
    /// What the networks read of the next observations.
    pub next_input: I,
    /// `[batch, 2]` next target vectors.
    pub next_vector: Tensor<2>,
    /// `[batch, 2]` the guide's action for each observation (0 where
    /// there is none), which the actor imitates with weight `imitation`.
    pub guide: Tensor<2>,
    /// `[batch, 1]`: 1 where the observation has a guide's action.
    pub guided: Tensor<2>,
}

/// What one update computed.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct UpdateStats {
    /// Mean squared TD error, summed over the two critics.
    pub critic_loss: f64,
    /// −Q1(s, π(s)), when the actor was updated this time.
    pub actor_loss: Option<f64>,
    /// Mean Q1 of the batch's actions.
    pub mean_q: f64,
}

/// What a critic step computed.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CriticStats {
    /// Mean squared TD error, summed over the two critics.
    pub loss: f64,
    /// Mean Q1 of the batch's actions.
    pub mean_q: f64,
}

/// The two critics, trained together by one optimiser.
#[derive(Module, Debug)]
pub struct TwinCritic<C: Module + ModuleDisplay> {
    q1: C,
    q2: C,
}

/// The learner's networks, their targets and optimisers. A clone is an
/// independent copy (see its `Clone`).
pub struct Td3<N: Networks> {
    config: Td3Config,
    networks: N,
    actor: N::Actor,
    critics: TwinCritic<N::Critic>,
    actor_target: N::Actor,
    critics_target: TwinCritic<N::Critic>,
    actor_optim: ModuleOptimizer,
    critic_optim: ModuleOptimizer,
    updates: u64,
    /// How the passes run on the networks' device.
    passes: Passes,
}

/// An independent copy, as the divergence guard's copy to roll back to
/// must be. A derived clone would share the BatchNorm running statistics:
/// Burn keeps them behind a lock that clones share, so every training pass
/// of the original would move the copy's statistics too. Parameters and
/// optimiser states are shared until written, and the CPU backend then
/// copies them instead of writing over them.
impl<N: Networks> Clone for Td3<N> {
    fn clone(&self) -> Self {
        Self {
            config: self.config.clone(),
            networks: self.networks.clone(),
            actor: self.actor.valid().train(),
            critics: self.critics.valid().train(),
            actor_target: self.actor_target.valid(),
            critics_target: self.critics_target.valid(),
            actor_optim: self.actor_optim.clone(),
            critic_optim: self.critic_optim.clone(),
            updates: self.updates,
            passes: self.passes,
        }
    }
}

impl<N: Networks> Td3<N> {
    /// One TD3 update on `batch`: a critic step, then the actor step when
    /// it is due.
    pub fn update(&mut self, batch: Minibatch<N::Input>) -> UpdateStats {
        let critic = self.critic_step(&batch);
        let actor_loss = self.actor_due().then(|| self.actor_step(batch));
        UpdateStats {
            critic_loss: critic.loss,
            actor_loss,
            mean_q: critic.mean_q,
        }
    }

    /// The critics' step: the TD target y from the target networks, then
    /// MSE(Q1(s, a), y) + MSE(Q2(s, a), y) and one Adam step of both.
    pub fn critic_step(&mut self, batch: &Minibatch<N::Input>) -> CriticStats {
        let passes = self.passes;
        passes.on_worker(|| {
            let (y, (q1, q2)) =
                passes.side_by_side(self.td_target_pass(batch), self.online_q_pass(batch));
            let mse = MseLoss::new();
            let loss_1 = mse.forward(q1.clone(), y.clone(), Reduction::Mean);
            let loss_2 = mse.forward(q2, y, Reduction::Mean);
            let stats = CriticStats {
                loss: scalar(&loss_1) + scalar(&loss_2),
                mean_q: scalar(&q1.mean()),
            };
            // Each critic's parameters get gradients from their own term
            // only: the two backward passes are independent.
            let (grads_1, grads_2) =
                passes.side_by_side(|| loss_1.backward(), || loss_2.backward());
            let grads = merged_gradients(grads_1, &self.critics.q1, grads_2, &self.critics.q2);
            let stand_in = self.critics_target.clone();
            let (optim, lr) = (&mut self.critic_optim, self.config.critic_lr);
            step_in_place(&mut self.critics, stand_in, optim, lr, grads);
            // The actor step needs no such call: its soft updates read both
            // networks' statistics.
            settle_running_statistics(&self.critics);
            self.updates += 1;
            stats
        })
    }

    /// Whether the delayed actor step is due after the critic steps so far
    /// (every `policy_delay`-th).
    pub fn actor_due(&self) -> bool {
        self.updates.is_multiple_of(self.config.policy_delay)
    }

    /// The delayed policy step, then the soft target updates
    /// θ' ← τ θ + (1 − τ) θ'; returns the actor's loss.
    pub fn actor_step(&mut self, batch: Minibatch<N::Input>) -> f64 {
        let passes = self.passes;
        passes.on_worker(|| {
            let loss = self.actor_loss(batch);
            let actor_loss = scalar(&loss);
            let grads = GradientsParams::from_grads(loss.backward(), &self.actor);
            let stand_in = self.actor_target.clone();
            let (optim, lr) = (&mut self.actor_optim, self.config.actor_lr);
            step_in_place(&mut self.actor, stand_in, optim, lr, grads);
            let tau = self.config.tau;
            soft_update_in_place(&mut self.actor_target, &self.actor, tau);
            soft_update_in_place(&mut self.critics_target, &self.critics, tau);
            actor_loss
        })
    }

    /// The TD target, as a pass to run beside others (no autodiff):
    /// y = r + γ^n (1 − terminated) min(Q1'(s', ã), Q2'(s', ã)), with the
    /// smoothed target action ã = clip(π'(s') + clip(ε, −c, c), −1, 1).
    fn td_target_pass(
        &self,
        batch: &Minibatch<N::Input>,
    ) -> impl FnOnce() -> Tensor<2> + Send + use<N> {
        let (actor, critics) = (self.actor_target.clone(), self.critics_target.clone());
        let (c, passes) = (self.config.clone(), self.passes);
        let Minibatch {
            reward,
            terminated,
            steps,
            next_input,
            next_vector,
            ..
        } = batch.clone();
        move || {
            let device = next_vector.device();
            let (next_input, next_vector) = (N::valid(next_input), next_vector.valid());
            let next_action = N::act(&actor, next_input.clone(), next_vector.clone());
            let noise = Tensor::<2>::random(
                next_action.shape(),
                Distribution::Normal(0.0, c.policy_noise),
                &next_action.device(),
            );
            let next_action = smoothed_target_action(next_action, noise, c.noise_clip);
            let (q1_next, q2_next) = passes.side_by_side(
                q_of::<N>(
                    critics.q1,
                    next_input.clone(),
                    next_vector.clone(),
                    next_action.clone(),
                ),
                q_of::<N>(critics.q2, next_input, next_vector, next_action),
            );
            let y = td_target(
                reward.valid() * c.reward_scale,
                terminated.valid(),
                steps.valid(),
                q1_next,
                q2_next,
                c.gamma,
            );
            Tensor::from_inner(y).to_device(&device)
        }
    }

    /// Q1(s, a) and Q2(s, a) of the batch's actions, as a pass.
    fn online_q_pass(
        &self,
        batch: &Minibatch<N::Input>,
    ) -> impl FnOnce() -> (Tensor<2>, Tensor<2>) + Send + use<N> {
        let (critics, passes) = (self.critics.clone(), self.passes);
        let Minibatch {
            input,
            vector,
            action,
            ..
        } = batch.clone();
        move || {
            passes.side_by_side(
                q_of::<N>(critics.q1, input.clone(), vector.clone(), action.clone()),
                q_of::<N>(critics.q2, input, vector, action),
            )
        }
    }

    /// The actor's loss: −Q1(s, π(s)), plus the optional action penalty and
    /// imitation of the guide.
    fn actor_loss(&self, batch: Minibatch<N::Input>) -> Tensor<1> {
        let c = &self.config;
        let Minibatch {
            input,
            vector,
            guide,
            guided,
            ..
        } = batch;
        // Q1's encoder features do not depend on π: computed detached
        // beside π(s), the backward pass skips Q1's encoder.
        let (actor, q1) = (self.actor.clone(), self.critics.q1.clone());
        let (pi, features) = self.passes.side_by_side(
            {
                let (input, vector) = (input.clone(), vector.clone());
                move || N::act(&actor, input, vector)
            },
            move || N::detach(N::features(&q1, input)),
        );
        let penalty = pi.clone().powi_scalar(2).mean() * c.action_l2;
        let q = N::value(&self.critics.q1, features, vector, pi.clone());
        if c.imitation > 0.0 {
            // TD3+BC: −Q / mean |Q| + w · mean over guided rows of |π − g|².
            let q_scale = q.clone().abs().mean().detach().add_scalar(1e-6);
            let miss = (pi - guide).powi_scalar(2).sum_dim(1) * guided;
            let imitation = miss.mean() * c.imitation;
            q.mean().neg().div(q_scale) + penalty + imitation
        } else {
            q.mean().neg() + penalty
        }
    }

    /// Fresh networks of `networks` on `device` (an autodiff device),
    /// once `config` is checked.
    pub fn new(config: Td3Config, networks: N, device: &Device) -> Result<Self, ConfigError> {
        config.validate()?;
        let actor = networks.actor(device);
        let critics = TwinCritic {
            q1: networks.critic(device),
            q2: networks.critic(device),
        };
        Ok(Self {
            networks,
            actor_target: actor.valid(),
            critics_target: critics.valid(),
            actor,
            critics,
            actor_optim: adam(&config),
            critic_optim: adam(&config),
            updates: 0,
            passes: Passes::new(cpu_kernels::is_cpu_backend(device)),
            config,
        })
    }

    /// The two critics, for inference (no autodiff): a snapshot carries
    /// them to check the policy's actions.
    pub fn critics(&self) -> [N::Critic; 2] {
        [self.critics.q1.valid(), self.critics.q2.valid()]
    }

    /// The scale of the critics' values: rewards times it.
    pub fn reward_scale(&self) -> f64 {
        self.config.reward_scale
    }

    /// The current policy, for inference (no autodiff).
    pub fn policy(&self) -> N::Actor {
        self.actor.valid()
    }

    /// The architecture trained.
    pub fn networks(&self) -> &N {
        &self.networks
    }

    /// Updates made so far.
    pub fn updates(&self) -> u64 {
        self.updates
    }
}

/// Target policy smoothing: a' = clip(π'(s') + clip(ε, −c, c), −1, 1).
pub fn smoothed_target_action(action: Tensor<2>, noise: Tensor<2>, noise_clip: f64) -> Tensor<2> {
    (action + noise.clamp(-noise_clip, noise_clip)).clamp(-1.0, 1.0)
}

/// Clipped double-Q target over `steps` steps (n-step returns; `reward`
/// their discounted sum): y = r + γ^steps (1 − terminated) min(Q1', Q2').
pub fn td_target(
    reward: Tensor<2>,
    terminated: Tensor<2>,
    steps: Tensor<2>,
    q1_next: Tensor<2>,
    q2_next: Tensor<2>,
    gamma: f64,
) -> Tensor<2> {
    let not_done = terminated.neg().add_scalar(1.0);
    // γ^steps; γ = 0 gives exp(−∞) = 0.
    let discount = (steps * gamma.ln()).exp();
    reward + not_done * discount * q1_next.min_pair(q2_next)
}

/// Q(s, a) of `critic`, as a pass to run.
fn q_of<N: Networks>(
    critic: N::Critic,
    input: N::Input,
    vector: Tensor<2>,
    action: Tensor<2>,
) -> impl FnOnce() -> Tensor<2> + Send {
    move || N::value(&critic, N::features(&critic, input), vector, action)
}

/// TD3's hyper-parameters; defaults are `docs/spec.md` §4.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Td3Config {
    /// Discount factor γ (the paper's best: 0.86).
    pub gamma: f64,
    /// Soft target update rate τ.
    pub tau: f64,
    /// Standard deviation of the target policy smoothing noise.
    pub policy_noise: f64,
    /// The smoothing noise is clipped to ±this.
    pub noise_clip: f64,
    /// Critic updates per actor update.
    pub policy_delay: u64,
    /// Adam learning rate of the actor.
    pub actor_lr: f64,
    /// Adam learning rate of the critics.
    pub critic_lr: f64,
    /// Rewards are multiplied by this before they enter the TD target (the
    /// optimal policy is unchanged; the critics' outputs shrink with it).
    pub reward_scale: f64,
    /// Adam's epsilon. PyTorch's 1e-8, not Burn's default 1e-5: an actor
    /// whose tanh saturates gets gradients far below 1e-5, and Burn's
    /// epsilon then all but stops it from ever leaving the corner.
    pub adam_epsilon: f64,
    /// Weight of the mean squared action in the actor's loss (as in
    /// OpenAI's HER baseline); keeps the tanh out of saturation while the
    /// critics are still wrong (0: the paper).
    pub action_l2: f64,
    /// Weight of the squared distance between the actor's action and the
    /// planner's on the same observation (0: none, the paper; 0.4: TD3+BC's
    /// α = 2.5). With it, the learner labels every arriving observation
    /// with the planner's action, and Q in the actor's loss is divided by
    /// its mean magnitude.
    pub imitation: f64,
    /// Steps of reward summed before the critics bootstrap (1: the paper;
    /// n-step returns beyond). Exploration noise makes the sums slightly
    /// off-policy; short ones carry a reward back n times faster.
    pub n_step: u32,
}

impl Default for Td3Config {
    fn default() -> Self {
        Self {
            gamma: 0.86,
            tau: 0.005,
            policy_noise: 0.2,
            noise_clip: 0.5,
            policy_delay: 2,
            actor_lr: 3e-4,
            critic_lr: 3e-4,
            reward_scale: 1.0,
            adam_epsilon: 1e-8,
            action_l2: 0.0,
            imitation: 0.0,
            n_step: 1,
        }
    }
}

impl Td3Config {
    /// Checks every field; the error names the first one out of range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let unit = [("td3.gamma", self.gamma), ("td3.tau", self.tau)];
        for (field, value) in unit {
            if !(0.0..=1.0).contains(&value) {
                return Err(ConfigError::invalid(
                    field,
                    format!("must be in [0, 1], got {value}"),
                ));
            }
        }
        let non_negative = [
            ("td3.policy_noise", self.policy_noise),
            ("td3.noise_clip", self.noise_clip),
            ("td3.action_l2", self.action_l2),
            ("td3.imitation", self.imitation),
        ];
        for (field, value) in non_negative {
            if !(value.is_finite() && value >= 0.0) {
                return Err(ConfigError::invalid(
                    field,
                    format!("must be finite and >= 0, got {value}"),
                ));
            }
        }
        for (field, value) in [
            ("td3.actor_lr", self.actor_lr),
            ("td3.critic_lr", self.critic_lr),
            ("td3.reward_scale", self.reward_scale),
            ("td3.adam_epsilon", self.adam_epsilon),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(ConfigError::invalid(
                    field,
                    format!("must be finite and > 0, got {value}"),
                ));
            }
        }
        if self.n_step == 0 {
            return Err(ConfigError::invalid("td3.n_step", "must be at least 1"));
        }
        if self.policy_delay == 0 {
            return Err(ConfigError::invalid(
                "td3.policy_delay",
                "must be at least 1",
            ));
        }
        Ok(())
    }
}

/// Adam with the configured epsilon: the optimiser the CPU kernels'
/// factored gradients require.
fn adam(config: &Td3Config) -> ModuleOptimizer {
    cpu_kernels::adam(config.adam_epsilon as f32)
}

impl<N: Networks> Td3<N> {
    /// Bytes the networks, their targets and Adam's two moments take.
    pub fn state_bytes(&self) -> usize {
        let parameters = self.actor.num_params() + self.critics.num_params();
        4 * size_of::<f32>() * parameters
    }

    /// The networks, targets and optimiser states as named burnpack byte
    /// buffers, for a checkpoint.
    pub fn save_state(&self) -> Result<Vec<(&'static str, Bytes)>, RecordError> {
        self.state_parts().collect()
    }

    /// [`Self::save_state`]'s buffers one at a time, each serialised when
    /// it is asked for.
    pub fn state_parts(
        &self,
    ) -> impl Iterator<Item = Result<(&'static str, Bytes), RecordError>> + '_ {
        type Make<'a> = Box<dyn Fn() -> Result<Bytes, RecordError> + 'a>;
        let parts: [(&'static str, Make<'_>); 6] = [
            (
                "actor",
                Box::new(|| self.actor.clone().into_record().into_bytes()),
            ),
            (
                "critics",
                Box::new(|| self.critics.clone().into_record().into_bytes()),
            ),
            (
                "actor_target",
                Box::new(|| self.actor_target.clone().into_record().into_bytes()),
            ),
            (
                "critics_target",
                Box::new(|| self.critics_target.clone().into_record().into_bytes()),
            ),
            ("actor_optim", Box::new(|| self.actor_optim.into_bytes())),
            ("critic_optim", Box::new(|| self.critic_optim.into_bytes())),
        ];
        parts
            .into_iter()
            .map(|(name, make)| make().map(|bytes| (name, bytes)))
    }

    /// Restores what [`Self::save_state`] saved, `updates` updates in;
    /// `part` finds a buffer by name. The networks must have the shapes the
    /// state was saved with.
    pub fn load_state<'a>(
        &mut self,
        part: impl Fn(&str) -> Option<&'a [u8]>,
        updates: u64,
    ) -> Result<(), RecordError> {
        let bytes = |name: &str| {
            part(name)
                .map(|b| Bytes::from_bytes_vec(b.to_vec()))
                .ok_or_else(|| RecordError::Io(format!("part `{name}` is missing")))
        };
        let module = |name: &str| ModuleRecord::from_bytes(bytes(name)?);
        self.actor = self.actor.clone().try_load_record(module("actor")?)?;
        self.critics = self.critics.clone().try_load_record(module("critics")?)?;
        self.actor_target = self
            .actor_target
            .clone()
            .try_load_record(module("actor_target")?)?;
        self.critics_target = self
            .critics_target
            .clone()
            .try_load_record(module("critics_target")?)?;
        let optimiser = |name: &str| OptimizerRecord::from_bytes(bytes(name)?);
        self.actor_optim = std::mem::replace(&mut self.actor_optim, adam(&self.config))
            .load_record(optimiser("actor_optim")?);
        self.critic_optim = std::mem::replace(&mut self.critic_optim, adam(&self.config))
            .load_record(optimiser("critic_optim")?);
        self.updates = updates;
        Ok(())
    }
}
