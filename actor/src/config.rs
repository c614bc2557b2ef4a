//! The actor's config file: an `[env]` table and an `[actor]` table.

use serde::{Deserialize, Serialize};
use std::path::Path;
use tweezer_config::{ConfigError, read_toml};
use tweezer_gym::{EnvConfig, SplitMix64};

/// The whole file.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ActorFile {
    /// The environment the actor steps (the learner's must match).
    pub env: EnvConfig,
    /// How the actor streams to the learner.
    pub actor: ActorConfig,
}

impl ActorFile {
    /// The defaults, or the validated contents of `path`.
    pub fn load(path: Option<&Path>) -> Result<Self, ConfigError> {
        let config: Self = match path {
            Some(path) => read_toml(path)?,
            None => Self::default(),
        };
        config.env.validate().map_err(|e| e.in_table("env"))?;
        config.actor.validate().map_err(|e| e.in_table("actor"))?;
        Ok(config)
    }

    /// The configuration as TOML, every default written out.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("every config field is TOML-representable")
    }
}

/// Streaming to the learner.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ActorConfig {
    /// The learner's gRPC address: `host:port`, or a URL whose scheme
    /// matches the security file (https://, or http:// when plaintext).
    pub learner: String,
    /// This actor's identity (letters, digits, `.`, `_`, `-`, `:`).
    pub id: String,
    /// Environments stepped together.
    pub envs: usize,
    /// Steps per batch sent.
    pub batch_steps: usize,
    /// Batches in flight before the actor waits for acknowledgements: the
    /// bound on its memory when the learner applies back-pressure.
    pub max_unacked: usize,
    /// Seed of the episodes and of the exploration noise.
    pub seed: u64,
    /// Mix the actor's id into `seed`: replicas started from one config
    /// (a Kubernetes Deployment, whose ids are pod names) then draw
    /// different episodes.
    pub seed_from_id: bool,
    /// Standard deviation of the Gaussian action noise (`docs/spec.md` §4:
    /// 0.1).
    pub noise: f64,
    /// Correlation of each environment's noise from one step to the next,
    /// in [0, 1): 0 draws it afresh every step (`docs/spec.md` §4).
    pub noise_correlation: f64,
    /// Environments driven by the planner instead of the policy, with the
    /// same noise: demonstrations that show the critics what dodging is
    /// worth from the first step (their episodes count in the training
    /// curves too). 0: none.
    pub demonstrators: usize,
    /// Address of the Prometheus endpoint (`GET /metrics`; the security
    /// file then needs a certificate, key and tokens); none unless set.
    pub metrics_listen: Option<std::net::SocketAddr>,
    /// First wait before reconnecting, ms; doubles up to `reconnect_max_ms`.
    pub reconnect_initial_ms: u64,
    /// Longest wait before reconnecting, ms.
    pub reconnect_max_ms: u64,
}

impl Default for ActorConfig {
    fn default() -> Self {
        Self {
            learner: "127.0.0.1:50051".into(),
            id: "actor-0".into(),
            envs: 16,
            batch_steps: 256,
            max_unacked: 4,
            seed: 0,
            seed_from_id: false,
            noise: 0.1,
            noise_correlation: 0.0,
            demonstrators: 0,
            metrics_listen: None,
            reconnect_initial_ms: 100,
            reconnect_max_ms: 10_000,
        }
    }
}

impl ActorConfig {
    /// The seed the actor runs with: `seed`, or with `seed_from_id` the
    /// seed mixed with a hash of `id` (FNV-1a, stable across builds).
    pub fn effective_seed(&self) -> u64 {
        if !self.seed_from_id {
            return self.seed;
        }
        let hash = self.id.bytes().fold(0xcbf2_9ce4_8422_2325_u64, |h, b| {
            (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
        });
        SplitMix64::derived(self.seed, hash).next_u64()
    }

    /// Checks every field; the error names the first one out of range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let invalid = |field: &str, reason: String| {
            Err(ConfigError::Invalid {
                field: field.into(),
                reason,
            })
        };
        let host_port = self
            .learner
            .strip_prefix("http://")
            .or_else(|| self.learner.strip_prefix("https://"))
            .unwrap_or(&self.learner);
        if self.learner.contains("://") && host_port.len() == self.learner.len()
            || !host_port.contains(':')
        {
            return invalid(
                "learner",
                format!(
                    "`{}` is not `host:port` or an http:// or https:// URL",
                    self.learner
                ),
            );
        }
        if let Err(e) = tweezer_proto::check_actor_id(&self.id) {
            return invalid("id", e.reason);
        }
        if self.envs == 0 {
            return invalid("envs", "must be at least 1".into());
        }
        if !(1..=tweezer_proto::MAX_BATCH_STEPS).contains(&self.batch_steps) {
            return invalid(
                "batch_steps",
                format!("must be 1 to {}", tweezer_proto::MAX_BATCH_STEPS),
            );
        }
        if self.demonstrators > self.envs {
            return invalid(
                "demonstrators",
                format!(
                    "{} is more than the {} environments (envs)",
                    self.demonstrators, self.envs
                ),
            );
        }
        if self.max_unacked == 0 {
            return invalid("max_unacked", "must be at least 1".into());
        }
        if !(self.noise.is_finite() && self.noise >= 0.0) {
            return invalid(
                "noise",
                format!("must be finite and >= 0, got {}", self.noise),
            );
        }
        if !(0.0..1.0).contains(&self.noise_correlation) {
            return invalid(
                "noise_correlation",
                format!("must lie in [0, 1), got {}", self.noise_correlation),
            );
        }
        if self.reconnect_initial_ms == 0 || self.reconnect_max_ms < self.reconnect_initial_ms {
            return invalid(
                "reconnect_max_ms",
                "reconnect_initial_ms must be >= 1 and reconnect_max_ms at least as long".into(),
            );
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_mixed_into_the_seed_give_replicas_their_own_episodes() {
        let pod = |id: &str| ActorConfig {
            id: id.into(),
            seed_from_id: true,
            ..ActorConfig::default()
        };
        let a = pod("tweezer-actor-7d9f-abcde").effective_seed();
        assert_eq!(a, pod("tweezer-actor-7d9f-abcde").effective_seed());
        assert_ne!(a, pod("tweezer-actor-7d9f-fghij").effective_seed());
        let plain = ActorConfig {
            seed: 42,
            ..ActorConfig::default()
        };
        assert_eq!(plain.effective_seed(), 42);
    }

    #[test]
    fn demonstrators_must_be_environments_of_the_actor() {
        let config = |demonstrators| ActorConfig {
            envs: 4,
            demonstrators,
            ..ActorConfig::default()
        };
        config(4).validate().unwrap();
        let err = config(5).validate().unwrap_err().to_string();
        assert!(err.contains("demonstrators"), "{err}");
    }

    #[test]
    fn noise_correlation_must_lie_below_one() {
        let config = |noise_correlation| ActorConfig {
            noise_correlation,
            ..ActorConfig::default()
        };
        config(0.0).validate().unwrap();
        config(0.95).validate().unwrap();
        for bad in [1.0, -0.1, f64::NAN] {
            let err = config(bad).validate().unwrap_err().to_string();
            assert!(
                err.contains("noise_correlation") && err.contains("[0, 1)"),
                "{err}"
            );
        }
    }
}
