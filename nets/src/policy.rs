//! A network as a `gym::Policy`, whichever architecture a snapshot holds:
//! observations become one batch of the network's inputs (rendered images
//! or sphere sets) and the actor runs once per call.

use crate::networks::Networks;
use crate::snapshot::{SnapshotError, SnapshotInfo, decode, read_info};
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
/// device without autodiff (BatchNorm uses its running statistics).
pub struct NetworkPolicy(Box<dyn Policy + Send>);

impl std::fmt::Debug for NetworkPolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("NetworkPolicy")
    }
}

/// An actor of `N` and what makes its inputs.
struct Inference<N: Networks> {
    networks: N,
    actor: N::Actor,
    device: Device,
}

impl NetworkPolicy {
    /// A policy from an actor of `networks`.
    pub fn new<N: Networks>(networks: N, actor: N::Actor, device: Device) -> Self {
        Self(Box::new(Inference {
            networks,
            actor,
            device,
        }))
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
            let (actor, info) = decode(bytes, &networks, device)?;
            (NetworkPolicy::new(networks, actor, device.clone()), info)
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
        for (action, xy) in actions.iter_mut().zip(out.chunks_exact(2)) {
            *action = Action::clipped(xy[0], xy[1]).unwrap_or(Action::ZERO);
        }
    }
}
