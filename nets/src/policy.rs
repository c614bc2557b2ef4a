//! A network as a `gym::Policy`, whichever architecture a snapshot holds:
//! observations become one batch of the network's inputs (rendered images
//! or sphere sets) and the actor runs once per call. Where the snapshot
//! carries the learner's critics, they check the actor's action
//! ([`crate::critic_search`]).

use crate::critic_search;
use crate::networks::Networks;
use crate::snapshot::{Decoded, SnapshotError, SnapshotInfo, decode, read_info};
use crate::spheres::Scene;
use burn::tensor::{Device, Tensor, TensorData};
use std::path::Path;
use tweezer_config::ConfigError;
use tweezer_gym::{Action, EnvConfig, Observation, Policy};

/// A snapshot file that cannot become a policy.
#[derive(Debug, thiserror::Error)]
pub enum PolicyFileError {
    /// The file cannot be read.
    #[error("cannot read snapshot {path}: {source}")]
    Read {
        /// The file.
        path: String,
        /// The operating system's reason.
        source: std::io::Error,
    },
    /// The file is not a usable snapshot.
    #[error("cannot use snapshot {path}: {source}")]
    Snapshot {
        /// The file.
        path: String,
        /// What is wrong with it.
        source: SnapshotError,
    },
    /// The environment config has no renderer.
    #[error(transparent)]
    Config(#[from] ConfigError),
}

/// A snapshot that cannot drive an environment.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// The snapshot is unusable or of another network.
    #[error(transparent)]
    Snapshot(#[from] SnapshotError),
    /// The environment config has no renderer.
    #[error(transparent)]
    Config(#[from] ConfigError),
}

/// An actor network choosing actions for batches of observations, on a
/// device without autodiff (BatchNorm uses its running statistics), with
/// the learner's critics checking its choice where the snapshot has them.
pub struct NetworkPolicy(Box<dyn Acting>);

/// What [`NetworkPolicy`] needs of the networks it hides.
trait Acting: Policy + Send {
    /// Whether the critics check the actor's actions.
    fn has_critics(&self) -> bool;
    /// Drops the critics: the actor acts alone.
    fn drop_critics(&mut self);
}

impl std::fmt::Debug for NetworkPolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("NetworkPolicy")
    }
}

/// An actor of `N`, the critics that check it, and what makes its inputs.
struct Inference<N: Networks> {
    networks: N,
    actor: N::Actor,
    check: Option<Check<N>>,
    device: Device,
}

/// The learner's critics and the margin by which they must prefer a
/// candidate to the actor's action ([`critic_search::choose`]).
struct Check<N: Networks> {
    critics: [N::Critic; 2],
    margin: f32,
}

impl NetworkPolicy {
    /// A policy from an actor of `networks`, acting alone.
    pub fn new<N: Networks>(networks: N, actor: N::Actor, device: Device) -> Self {
        Self::checked(networks, actor, None, None, device)
    }

    /// A policy from an actor of `networks` whose actions `critics`, where
    /// given, check; their values are rewards times `reward_scale`, where
    /// known ([`critic_search::margin`]).
    pub fn checked<N: Networks>(
        networks: N,
        actor: N::Actor,
        critics: Option<[N::Critic; 2]>,
        reward_scale: Option<f64>,
        device: Device,
    ) -> Self {
        let margin = critic_search::margin(reward_scale);
        Self(Box::new(Inference {
            networks,
            actor,
            check: critics.map(|critics| Check { critics, margin }),
            device,
        }))
    }

    /// This policy with the actor acting alone, as TD3 explores and as the
    /// Python package acts.
    pub fn actor_alone(mut self) -> Self {
        self.0.drop_critics();
        self
    }

    /// Whether the learner's critics check the actor's actions.
    pub fn has_critics(&self) -> bool {
        self.0.has_critics()
    }

    /// Loads a snapshot of either architecture for the observations of
    /// `env`: a CNN must take the resolution `env` renders; a set network
    /// takes `env`'s field of view at the scale it was trained at.
    pub fn from_snapshot(
        bytes: &[u8],
        env: &EnvConfig,
        device: &Device,
    ) -> Result<(Self, SnapshotInfo), LoadError> {
        let networks = read_info(bytes)?.architecture.networks(env)?;
        Ok(crate::with_networks!(networks, |networks| {
            let Decoded {
                actor,
                critics,
                critic_reward_scale,
                info,
            } = decode(bytes, &networks, device)?;
            let policy = NetworkPolicy::checked(
                networks,
                actor,
                critics,
                critic_reward_scale,
                device.clone(),
            );
            (policy, info)
        }))
    }

    /// Loads the snapshot file at `path` for the observations of `env`.
    pub fn from_file(
        path: &Path,
        env: &EnvConfig,
        device: &Device,
    ) -> Result<(Self, SnapshotInfo), PolicyFileError> {
        let name = || path.display().to_string();
        let bytes = std::fs::read(path).map_err(|source| PolicyFileError::Read {
            path: name(),
            source,
        })?;
        Self::from_snapshot(&bytes, env, device).map_err(|e| match e {
            LoadError::Snapshot(source) => PolicyFileError::Snapshot {
                path: name(),
                source,
            },
            LoadError::Config(e) => PolicyFileError::Config(e),
        })
    }
}

impl Policy for NetworkPolicy {
    fn act(&mut self, observations: &[&Observation], actions: &mut [Action]) {
        self.0.act(observations, actions);
    }
}

impl<N: Networks> Acting for Inference<N> {
    fn has_critics(&self) -> bool {
        self.check.is_some()
    }

    fn drop_critics(&mut self) {
        self.check = None;
    }
}

impl<N: Networks> Policy for Inference<N> {
    /// A network that outputs NaN (broken weights) stands still rather than
    /// driving the stage anywhere.
    fn act(&mut self, observations: &[&Observation], actions: &mut [Action]) {
        let n = observations.len();
        if n == 0 {
            return;
        }
        let vectors: Vec<f32> = observations.iter().flat_map(|o| o.vector).collect();
        let scenes = observations.iter().map(|o| Scene::of(o));
        let input = self.networks.input(scenes, &self.device);
        let vector = Tensor::<2>::from_data(TensorData::new(vectors, [n, 2]), &self.device);
        let out: Vec<f32> = N::act(&self.actor, input, vector)
            .into_data()
            .try_to_vec()
            .expect("the actor outputs f32");
        let mut chosen: Vec<[f32; 2]> = out.chunks_exact(2).map(|xy| [xy[0], xy[1]]).collect();
        if let Some(Check { critics, margin }) = &self.check {
            chosen = critic_search::choose(
                &self.networks,
                critics,
                *margin,
                observations,
                &chosen,
                &self.device,
            );
        }
        for (action, [x, y]) in actions.iter_mut().zip(chosen) {
            *action = Action::clipped(x, y).unwrap_or(Action::ZERO);
        }
    }
}
