//! The hardware agent's configuration file: the environment it shares with
//! training, segmentation, the stages, the control loop, the policy, the
//! camera, the overlay, the service, and the digital twin.

use crate::control::ControlConfig;
use crate::overlay::OverlayConfig;
use crate::policy_source::PolicyConfig;
use crate::twin::TwinConfig;
use kdc101::StagesConfig;
use serde::{Deserialize, Serialize};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use tweezer_config::{ConfigError, read_toml};
use tweezer_gym::EnvConfig;
use tweezer_vision::SegmentConfig;
use tweezer_vision::frame_stream::StreamConfig;
use tweezer_vision::genicam::GenicamConfig;

/// Everything `hardware-agent` reads from its `--config` file; a missing
/// table or field takes its default.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AgentConfig {
    /// The virtual environment the policy was trained in (FOV, sphere size,
    /// target distance and radii, time limit, image resolution).
    pub env: EnvConfig,
    /// Finding spheres in camera frames.
    pub segmentation: SegmentConfig,
    /// The two stages and their calibration.
    pub stages: StagesConfig,
    /// The control loop.
    pub control: ControlConfig,
    /// Where the policy comes from.
    pub policy: PolicyConfig,
    /// Where frames come from.
    pub camera: CameraConfig,
    /// Virtual obstacles (the augmented environment).
    pub overlay: OverlayConfig,
    /// The gRPC service.
    pub service: ServiceConfig,
    /// Where episode records go.
    pub records: RecordsConfig,
    /// The digital twin.
    pub twin: TwinConfig,
}

/// The `[service]` table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServiceConfig {
    /// Address the gRPC service listens on.
    pub listen: SocketAddr,
    /// Address of the Prometheus endpoint (`GET /metrics`, secured like
    /// the gRPC service); none unless set.
    pub metrics_listen: Option<SocketAddr>,
}

impl Default for ServiceConfig {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 50061)),
            metrics_listen: None,
        }
    }
}

/// The `[records]` table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RecordsConfig {
    /// Directory of episode records (one JSON-lines file and one picture
    /// per episode).
    pub dir: PathBuf,
}

impl Default for RecordsConfig {
    fn default() -> Self {
        Self {
            dir: PathBuf::from("episodes"),
        }
    }
}

impl AgentConfig {
    /// The defaults, or the validated contents of `path`.
    pub fn load(path: Option<&Path>) -> Result<Self, ConfigError> {
        let Some(path) = path else {
            return Ok(Self::default());
        };
        let config: Self = read_toml(path)?;
        config.validate().map_err(|e| match e {
            ConfigError::Invalid { field, reason } => ConfigError::Invalid {
                field,
                reason: format!("{reason} (in {})", path.display()),
            },
            other => other,
        })?;
        Ok(config)
    }

    /// Checks every table.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.env.validate().map_err(|e| e.in_table("env"))?;
        self.segmentation
            .validate()
            .map_err(|e| ConfigError::invalid("segmentation", e.to_string()))?;
        for (table, check) in [
            ("stages", self.stages.validate()),
            ("control", self.control.validate()),
            ("policy", self.policy.validate()),
            ("overlay", self.overlay.validate()),
            ("twin", self.twin.validate()),
            ("camera.genicam", self.camera.genicam.validate()),
            ("camera.stream", self.camera.stream_validate()),
        ] {
            check.map_err(|e| e.in_table(table))?;
        }
        Ok(())
    }

    /// The configuration as TOML, every default written out.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("every config field is TOML-representable")
    }
}

/// Where frames come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraSource {
    /// A directory of frame files, replayed in name order.
    Replay,
    /// The digital twin's camera (what `--twin` selects).
    Twin,
    /// A GigE Vision or USB3 Vision camera through Aravis
    /// (`[camera.genicam]`; a build with the `aravis` feature).
    Genicam,
    /// Frames another program writes (`[camera.stream]`).
    Stream,
}

impl CameraSource {
    /// The name the configuration uses.
    pub fn name(self) -> &'static str {
        match self {
            Self::Replay => "replay",
            Self::Twin => "twin",
            Self::Genicam => "genicam",
            Self::Stream => "stream",
        }
    }
}

/// The `[camera]` table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraConfig {
    /// The backend.
    pub source: CameraSource,
    /// The directory of frames (source = "replay").
    pub dir: PathBuf,
    /// Whether the replay starts over after the last frame.
    #[serde(rename = "loop")]
    pub looping: bool,
    /// The GenICam camera (source = "genicam").
    pub genicam: GenicamConfig,
    /// The program feeding frames (source = "stream").
    pub stream: StreamConfig,
}

impl CameraConfig {
    /// The `[camera.stream]` table is checked when it is the source.
    fn stream_validate(&self) -> Result<(), ConfigError> {
        match self.source {
            CameraSource::Stream => self.stream.validate(),
            _ => Ok(()),
        }
    }
}

impl Default for CameraConfig {
    fn default() -> Self {
        Self {
            source: CameraSource::Twin,
            dir: PathBuf::from("frames"),
            looping: false,
            genicam: GenicamConfig::default(),
            stream: StreamConfig::default(),
        }
    }
}
