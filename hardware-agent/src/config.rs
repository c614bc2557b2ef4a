//! The hardware agent's configuration file: the environment it shares with
//! training, segmentation, and the digital twin.

use crate::segment::SegmentConfig;
use crate::twin::OpticsConfig;
use serde::{Deserialize, Serialize};
use std::path::Path;
use tweezer_gym::{ConfigError, EnvConfig, read_toml};

/// Everything `hardware-agent` reads from its `--config` file; a missing
/// table or field takes its default.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AgentConfig {
    /// The virtual environment the policy was trained in (FOV, sphere size,
    /// target vector scaling, image resolution).
    pub env: EnvConfig,
    /// Finding spheres in camera frames.
    pub segmentation: SegmentConfig,
    /// The digital twin.
    pub twin: TwinConfig,
}

/// The digital twin of the microscope.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TwinConfig {
    /// How its camera renders frames.
    pub optics: OpticsConfig,
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
                field: format!("{field} (in {})", path.display()),
                reason,
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
            .map_err(|e| invalid("segmentation", e.to_string()))?;
        self.twin
            .optics
            .validate()
            .map_err(|reason| invalid("twin.optics", reason))
    }

    /// The configuration as TOML, every default written out.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("every config field is TOML-representable")
    }
}

fn invalid(field: &str, reason: String) -> ConfigError {
    ConfigError::Invalid {
        field: field.into(),
        reason,
    }
}
