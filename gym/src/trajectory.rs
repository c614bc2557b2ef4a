//! Recorded episodes, for pictures: the trap's path and every free sphere's.

use crate::action::Action;
use crate::config::EnvConfig;
use crate::env::EpisodeError;
use crate::env::{Env, Outcome, Target};
use crate::policy::Policy;
use tweezer_config::ConfigError;

/// One episode, step by step, in world px.
#[derive(Clone, Debug, PartialEq)]
pub struct Trajectory {
    /// The episode seed.
    pub seed: u64,
    /// FOV size in px.
    pub fov_px: [f64; 2],
    /// Sphere radius in px.
    pub radius: f64,
    /// World size in px.
    pub world_px: [f64; 2],
    /// Target position.
    pub target: [f64; 2],
    /// Trap position at each step, from step 0.
    pub trap: Vec<[f64; 2]>,
    /// Every free sphere's centre at each step, from step 0: `spheres[t][k]`.
    pub spheres: Vec<Vec<[f64; 2]>>,
    /// Actions taken.
    pub actions: Vec<Action>,
    /// How the episode ended.
    pub outcome: Outcome,
    /// Sum of rewards.
    pub episode_return: f64,
}

/// An episode that could not be recorded.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// The configuration is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The episode cannot start as asked.
    #[error(transparent)]
    Episode(#[from] EpisodeError),
}

/// Runs episode `seed` toward `target` with `policy`, recording everything.
pub fn record(
    config: &EnvConfig,
    seed: u64,
    target: Target,
    policy: &mut dyn Policy,
) -> Result<Trajectory, RecordError> {
    let mut env = Env::new(config.clone())?;
    env.reset_with_target(seed, target)?;
    let mut trajectory = Trajectory {
        seed,
        fov_px: [f64::from(config.fov_px[0]), f64::from(config.fov_px[1])],
        radius: config.sphere_radius_px(),
        world_px: config.world_px,
        target: env.target(),
        trap: vec![env.trap()],
        spheres: vec![env.free_sphere_positions()],
        actions: Vec::new(),
        outcome: Outcome::Running,
        episode_return: 0.0,
    };
    let mut action = [Action::ZERO];
    while env.outcome() == Outcome::Running {
        policy.act(&[env.observation()], &mut action);
        let step = env.step(action[0]).expect("the episode is running");
        trajectory.episode_return += step.reward;
        trajectory.actions.push(action[0]);
        trajectory.trap.push(env.trap());
        trajectory.spheres.push(env.free_sphere_positions());
    }
    trajectory.outcome = env.outcome();
    Ok(trajectory)
}
