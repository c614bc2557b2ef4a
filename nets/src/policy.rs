//! A network as a `gym::Policy`: observations are rendered by the shared
//! renderer into one batch and the actor runs once per call.

use crate::actor::Actor;
use crate::images::render_images;
use crate::snapshot::{SnapshotError, SnapshotInfo, decode};
use burn::tensor::{Device, Tensor, TensorData};
use std::path::Path;
use tweezer_config::ConfigError;
use tweezer_gym::{Action, EnvConfig, Observation, Policy, Renderer};

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

/// The actor network choosing actions for batches of observations, on a
/// device without autodiff (BatchNorm uses its running statistics).
#[derive(Debug)]
pub struct NetworkPolicy {
    actor: Actor,
    renderer: Renderer,
    device: Device,
}

impl NetworkPolicy {
    /// A policy from an actor and the renderer of its input resolution.
    pub fn new(actor: Actor, renderer: Renderer, device: Device) -> Self {
        Self {
            actor,
            renderer,
            device,
        }
    }

    /// Loads a snapshot for the renderer's image resolution.
    pub fn from_snapshot(
        bytes: &[u8],
        renderer: Renderer,
        device: &Device,
    ) -> Result<(Self, SnapshotInfo), SnapshotError> {
        let (actor, info) = decode(bytes, renderer.height(), renderer.width(), device)?;
        Ok((Self::new(actor, renderer, device.clone()), info))
    }

    /// Loads the snapshot file at `path` for the images of `env`.
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
        let renderer = Renderer::for_config(env)?;
        Self::from_snapshot(&bytes, renderer, device).map_err(|source| PolicyFileError::Snapshot {
            path: name(),
            source,
        })
    }
}

impl Policy for NetworkPolicy {
    /// A network that outputs NaN (broken weights) stands still rather than
    /// driving the stage anywhere.
    fn act(&mut self, observations: &[&Observation], actions: &mut [Action]) {
        let n = observations.len();
        if n == 0 {
            return;
        }
        let vectors: Vec<f32> = observations.iter().flat_map(|o| o.vector).collect();
        let centres = observations.iter().map(|o| o.centres.as_slice());
        let image = render_images(&self.renderer, centres, &self.device);
        let vector = Tensor::<2>::from_data(TensorData::new(vectors, [n, 2]), &self.device);
        let out: Vec<f32> = self
            .actor
            .forward(image, vector)
            .into_data()
            .try_to_vec()
            .expect("the actor outputs f32");
        for (action, xy) in actions.iter_mut().zip(out.chunks_exact(2)) {
            *action = Action::clipped(xy[0], xy[1]).unwrap_or(Action::ZERO);
        }
    }
}
