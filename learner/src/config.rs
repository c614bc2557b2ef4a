//! The learner's config file: an `[env]` table and a `[learner]` table,
//! every field defaulting to the values of `docs/spec.md`.

use crate::ingest::limiter::LimiterConfig;
use crate::replay::ReplayConfig;
use crate::training::divergence::Rollback;
use crate::training::td3::Td3Config;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use tweezer_config::{ConfigError, read_toml};
use tweezer_gym::EnvConfig;
use tweezer_nets::{ActionJoin, Architecture, Frame, Pooling, SetShape, SphereInputs};

/// The whole file.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LearnerFile {
    /// The environment the actors run (the learner renders its images).
    pub env: EnvConfig,
    /// The learner itself.
    pub learner: LearnerConfig,
}

impl LearnerFile {
    /// The defaults, or the validated contents of `path`.
    pub fn load(path: Option<&Path>) -> Result<Self, ConfigError> {
        let config: Self = match path {
            Some(path) => read_toml(path)?,
            None => Self::default(),
        };
        config.validate()?;
        Ok(config)
    }

    /// The config of the run in `dir`, as its learner wrote it; a
    /// directory without one is said not to be a run directory.
    pub fn of_run(dir: &Path) -> anyhow::Result<Self> {
        let path = crate::persistence::run_dir::RunDir::new(dir).config();
        if !path.is_file() {
            anyhow::bail!(
                "{} is not a run directory: it has no {} (a learner writes one when it starts a run)",
                dir.display(),
                path.file_name().unwrap_or_default().to_string_lossy()
            );
        }
        Ok(Self::load(Some(&path))?)
    }

    /// Checks every field; the error names the first one out of range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        validate_tables(&self.env, &self.learner)
    }

    /// The configuration as TOML, every default written out.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("every config field is TOML-representable")
    }
}

/// Checks a file's `[env]` and `[learner]` tables and that the network
/// takes the env's images; the error names the first field out of range.
pub fn validate_tables(env: &EnvConfig, learner: &LearnerConfig) -> Result<(), ConfigError> {
    env.validate().map_err(|e| e.in_table("env"))?;
    learner.validate().map_err(|e| e.in_table("learner"))?;
    learner.network.check_fits(env)
}

/// How the learner serves, trains and keeps its state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LearnerConfig {
    /// Address the gRPC service listens on.
    pub listen: SocketAddr,
    /// Address of the Prometheus endpoint (`GET /metrics`, secured like
    /// the gRPC service); none unless set.
    pub metrics_listen: Option<SocketAddr>,
    /// Directory for the config, snapshots, checkpoints and metrics.
    pub run_dir: PathBuf,
    /// Where the networks train.
    pub device: DeviceChoice,
    /// Which networks train.
    pub network: NetworkConfig,
    /// Seed of the replay sampler and of the networks' initial weights.
    pub seed: u64,
    /// Transitions per update (`docs/spec.md` §4: 32).
    pub batch_size: usize,
    /// Transitions taken with uniformly random actions before the actors
    /// switch to the policy (`docs/spec.md` §4: 10,000).
    pub uniform_steps: u64,
    /// Updates after which the learner makes no more (0: no limit): the
    /// policy at a fixed number of updates, whatever the machine's speed.
    /// It goes on serving, and publishes a snapshot at exactly this many.
    pub max_updates: u64,
    /// Whether each sampled step is shown mirrored about a random choice of
    /// the stage's axes (`training::mirror`): four steps for one.
    pub mirror: bool,
    /// The replay table.
    pub replay: ReplayConfig,
    /// TD3.
    pub td3: Td3Config,
    /// Updates per inserted transition.
    pub limiter: LimiterConfig,
    /// Policy snapshots.
    pub snapshots: SnapshotConfig,
    /// Checkpoints.
    pub checkpoints: CheckpointConfig,
    /// What a diverged update rolls back to.
    pub rollback: Rollback,
    /// Updates between two lines of the metrics file.
    pub metrics_every_updates: u64,
    /// Largest step batch the gRPC service decodes, in bytes; actors learn
    /// it when they connect and split their batches to fit.
    pub max_message_bytes: usize,
}

/// Smallest `max_message_bytes`: room for any one step of a dense field.
const MIN_MESSAGE_BYTES: usize = 1 << 20;

/// Largest `max_message_bytes`.
const MAX_MESSAGE_BYTES: usize = 1 << 30;

impl Default for LearnerConfig {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 50051)),
            metrics_listen: None,
            run_dir: PathBuf::from("runs/learner"),
            device: DeviceChoice::Flex,
            network: NetworkConfig::Paper,
            seed: 0,
            batch_size: 32,
            uniform_steps: 10_000,
            max_updates: 0,
            mirror: false,
            replay: ReplayConfig::default(),
            td3: Td3Config::default(),
            limiter: LimiterConfig::default(),
            snapshots: SnapshotConfig::default(),
            checkpoints: CheckpointConfig::default(),
            rollback: Rollback::Auto,
            metrics_every_updates: 100,
            max_message_bytes: 16 << 20,
        }
    }
}

impl LearnerConfig {
    /// Checks every field; the error names the first one out of range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let invalid = |field: &str, reason: &str| {
            Err(ConfigError::Invalid {
                field: field.into(),
                reason: reason.into(),
            })
        };
        if self.batch_size == 0 {
            return invalid("batch_size", "must be at least 1");
        }
        if self.replay.capacity == 0 {
            return invalid("replay.capacity", "must be at least 1");
        }
        if self.replay.centres_per_transition == 0 {
            return invalid("replay.centres_per_transition", "must be at least 1");
        }
        if self.snapshots.every_updates == 0 {
            return invalid("snapshots.every_updates", "must be at least 1");
        }
        if self.snapshots.keep == 0 {
            return invalid("snapshots.keep", "must be at least 1");
        }
        if self.checkpoints.keep == 0 {
            return invalid("checkpoints.keep", "must be at least 1");
        }
        if !(self.checkpoints.every_seconds.is_finite() && self.checkpoints.every_seconds >= 0.0) {
            return invalid(
                "checkpoints.every_seconds",
                "must be finite and >= 0 (0: only on shutdown)",
            );
        }
        if self.metrics_every_updates == 0 {
            return invalid("metrics_every_updates", "must be at least 1");
        }
        if !(MIN_MESSAGE_BYTES..=MAX_MESSAGE_BYTES).contains(&self.max_message_bytes) {
            return invalid(
                "max_message_bytes",
                "must be between 1 MiB (1048576) and 1 GiB (1073741824)",
            );
        }
        self.network.validate()?;
        self.td3.validate()?;
        self.limiter.validate()?;
        // `device` is not opened here: `experiment`, which reads this
        // config without training on it, need not be built with the
        // learner's GPU feature. `learner config`, `serve` and `bench` open
        // it and refuse one their build lacks.
        Ok(())
    }
}

/// The `[learner.network]` table: the paper's CNN (the default) or the
/// set network that reads sphere centres.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum NetworkConfig {
    /// The paper's CNN on images of `env.image`'s resolution.
    Paper,
    /// The set network on the centres of `env.fov_px`.
    Set(SetNetworkConfig),
}

/// Read by `kind` first, then the rest as that kind's fields, one by one:
/// serde's own reading of a tagged table reports a bad field at the table's
/// first line without naming it; this names it
/// (`learner.network.sphere_hidden`).
impl<'de> Deserialize<'de> for NetworkConfig {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let mut table = toml::Table::deserialize(deserializer)?;
        let kind = table
            .remove("kind")
            .ok_or_else(|| D::Error::custom("`kind` is missing: \"paper\" (the CNN) or \"set\""))?;
        match kind.as_str() {
            Some("paper") => match table.keys().next() {
                None => Ok(Self::Paper),
                Some(key) => Err(D::Error::custom(format!(
                    "`{key}` is a set network's field, and kind = \"paper\" takes none"
                ))),
            },
            Some("set") => {
                // Field by field first, so that an error can name its field.
                for (key, value) in &table {
                    let one = toml::Table::from_iter([(key.clone(), value.clone())]);
                    if let Err(e) = SetNetworkConfig::deserialize(toml::Value::Table(one)) {
                        return Err(D::Error::custom(format!(
                            "learner.network.{key}: {}",
                            e.message()
                        )));
                    }
                }
                SetNetworkConfig::deserialize(toml::Value::Table(table))
                    .map(Self::Set)
                    .map_err(|e| D::Error::custom(e.message()))
            }
            _ => Err(D::Error::custom(format!(
                "kind = {kind} is not \"paper\" or \"set\""
            ))),
        }
    }
}

/// The set network's hyper-parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SetNetworkConfig {
    /// Width of the per-sphere MLP's two layers.
    pub sphere_hidden: usize,
    /// Width of the two layers after pooling.
    pub head_hidden: usize,
    /// `max_mean`, `max` or `mean`.
    pub pooling: Pooling,
    /// Most spheres a set holds; a scene with more keeps the nearest.
    pub max_spheres: usize,
    /// `positions`, or `motion`: each sphere's displacement since the
    /// previous step too.
    pub inputs: SphereInputs,
    /// `pooled`, or `per_sphere`: the critic's action joins each sphere's
    /// first layer too.
    pub action_join: ActionJoin,
    /// LayerNorm in the critic's layers after pooling.
    pub critic_layer_norm: bool,
    /// `stage`, or `goal`: the scene, the target vector and the action
    /// along and across the heading to the target.
    pub frame: Frame,
}

impl Default for SetNetworkConfig {
    /// [`SetShape::new`]'s.
    fn default() -> Self {
        let shape = SetShape::new([1, 1]);
        Self {
            sphere_hidden: shape.sphere_hidden,
            head_hidden: shape.head_hidden,
            pooling: shape.pooling,
            max_spheres: shape.max_spheres,
            inputs: shape.inputs,
            action_join: shape.action_join,
            critic_layer_norm: shape.critic_layer_norm,
            frame: shape.frame,
        }
    }
}

impl NetworkConfig {
    /// The architecture this config trains for `env`.
    pub fn architecture(&self, env: &EnvConfig) -> Architecture {
        match self {
            Self::Paper => Architecture::Paper {
                height: env.image.height as usize,
                width: env.image.width as usize,
            },
            Self::Set(s) => Architecture::Set(SetShape {
                sphere_hidden: s.sphere_hidden,
                head_hidden: s.head_hidden,
                pooling: s.pooling,
                max_spheres: s.max_spheres,
                fov_px: env.fov_px,
                inputs: s.inputs,
                action_join: s.action_join,
                critic_layer_norm: s.critic_layer_norm,
                frame: s.frame,
                motion_unit_px: SetShape::motion_unit_for(env),
            }),
        }
    }

    /// Checks that the network takes `env`'s images (the paper network's
    /// convolutions need a few pixels each way); the error names
    /// `env.image`.
    fn check_fits(&self, env: &EnvConfig) -> Result<(), ConfigError> {
        match self {
            Self::Paper => self
                .architecture(env)
                .validate()
                .map_err(|e| ConfigError::invalid("env.image", e.to_string())),
            Self::Set(_) => Ok(()),
        }
    }

    /// Checks the set network's sizes.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let Self::Set(s) = self else { return Ok(()) };
        for (field, value) in [
            ("network.sphere_hidden", s.sphere_hidden),
            ("network.head_hidden", s.head_hidden),
            ("network.max_spheres", s.max_spheres),
        ] {
            if !(1..=4096).contains(&value) {
                return Err(ConfigError::invalid(field, "must lie in [1, 4096]"));
            }
        }
        Ok(())
    }
}

/// Policy snapshot publishing.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SnapshotConfig {
    /// Updates between snapshots.
    pub every_updates: u64,
    /// Snapshot files kept on disk besides the best one.
    pub keep: usize,
}

impl Default for SnapshotConfig {
    fn default() -> Self {
        Self {
            every_updates: 1_000,
            keep: 5,
        }
    }
}

/// Checkpoints of the whole learner state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CheckpointConfig {
    /// Seconds between periodic checkpoints; 0 writes one only on shutdown.
    pub every_seconds: f64,
    /// Checkpoints kept; older ones are deleted once a newer one is safe.
    pub keep: usize,
    /// Include the replay (large: ~180 bytes per transition).
    pub replay: bool,
}

impl Default for CheckpointConfig {
    fn default() -> Self {
        Self {
            every_seconds: 600.0,
            keep: 3,
            replay: false,
        }
    }
}

/// The device the networks train on. GPU devices need the learner built
/// with the matching cargo feature.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DeviceChoice {
    /// Burn's pure-Rust CPU backend.
    Flex,
    /// The first CUDA GPU (feature `cuda`).
    Cuda,
    /// The default wgpu adapter on Vulkan, Metal or DirectX 12 (feature
    /// `wgpu`); never OpenGL, whose drivers lack what Burn's kernels use.
    Wgpu,
}

impl DeviceChoice {
    /// The device, or an error naming the cargo feature this build lacks.
    pub fn device(self) -> Result<Device, ConfigError> {
        match self {
            Self::Flex => Ok(Device::flex()),
            #[cfg(feature = "cuda")]
            Self::Cuda => crate::training::gpu_devices::cuda(),
            #[cfg(not(feature = "cuda"))]
            Self::Cuda => Err(missing("cuda")),
            #[cfg(feature = "wgpu")]
            Self::Wgpu => crate::training::gpu_devices::wgpu(),
            #[cfg(not(feature = "wgpu"))]
            Self::Wgpu => Err(missing("wgpu")),
        }
    }
}

impl DeviceChoice {
    /// `learner.device` as the config file spells it (`wgpu`).
    pub fn name(self) -> String {
        format!("{self:?}").to_lowercase()
    }

    /// The device for reports: the choice and, on a GPU, the part Burn
    /// opened (`wgpu (llvmpipe (LLVM 15.0.6, 256 bits))`).
    pub fn describe(self, device: &Device) -> String {
        let name = self.name();
        #[cfg(any(feature = "cuda", feature = "wgpu"))]
        if let Some(identity) = device.identity() {
            return format!("{name} ({})", identity.name);
        }
        let _ = device;
        name
    }
}

#[cfg(not(all(feature = "cuda", feature = "wgpu")))]
fn missing(feature: &str) -> ConfigError {
    // cuda's LLVM comes from PyPI through the script (docs/configuration.md).
    let script = if feature == "cuda" {
        "deploy/cuda/with-llvm.sh "
    } else {
        ""
    };
    ConfigError::Invalid {
        field: "learner.device".into(),
        reason: format!(
            "this learner was built without the `{feature}` feature; rebuild with `{script}cargo build --release --locked -p tweezer-learner --features {feature}`"
        ),
    }
}
