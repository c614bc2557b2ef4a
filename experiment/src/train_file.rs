//! What `experiment train` runs: a train file (`[env]`, `[learner]`, `[actor]`,
//! `[train]`, `[sweep]`), from a preset or the operator's TOML.

use crate::sweep::SweepConfig;
use serde::{Deserialize, Serialize};
use std::path::Path;
use tweezer_actor::config::ActorConfig;
use tweezer_config::{ConfigError, read_toml};
use tweezer_gym::{EnvConfig, Seeds};
use tweezer_learner::config::LearnerConfig;

/// The presets, by name: the paper's settings (`docs/spec.md`), its CNN sized
/// for a 2-core CPU, and the set network at the full field of view.
const PRESETS: [(&str, &str); 3] = [
    ("paper", include_str!("../presets/paper.toml")),
    ("quick", include_str!("../presets/quick.toml")),
    ("lean", include_str!("../presets/lean.toml")),
];

/// Keys of the `[actor]` table that `experiment train` sets for each actor.
const SET_PER_ACTOR: [&str; 3] = ["learner", "id", "seed"];

/// A whole training run.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainFile {
    /// The environment (actors step it, the learner renders it).
    pub env: EnvConfig,
    /// The learner.
    pub learner: LearnerConfig,
    /// Each actor's `[actor]` table; `learner`, `id` and `seed` are set per
    /// actor. Checked here as the actor reads it, before anything starts.
    pub actor: toml::Table,
    /// The run itself.
    pub train: TrainConfig,
    /// Values to sweep: one run per combination.
    pub sweep: SweepConfig,
}

/// How long, with how many actors, and how the run is evaluated.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// The setting's name in reports (runs with one label are averaged);
    /// empty: the run directory's name.
    pub label: String,
    /// Actor processes.
    pub actors: usize,
    /// Minutes of training; 0: until SIGINT or SIGTERM.
    pub minutes: f64,
    /// Held-out episode seeds the best snapshot is evaluated on.
    pub eval_seeds: String,
    /// Seeds, apart from the held-out ones, on which the kept snapshots
    /// are compared to choose the one evaluated; empty: the one published at
    /// the best rolling return.
    pub validation_seeds: String,
    /// Episodes evaluated side by side.
    pub eval_batch: usize,
    /// Episode seeds drawn as Figs. 5 (each) and 6 (the first).
    pub picture_seeds: String,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            label: String::new(),
            actors: 1,
            minutes: 0.0,
            eval_seeds: "100000..100200".into(),
            validation_seeds: String::new(),
            eval_batch: 64,
            picture_seeds: "100000..100003".into(),
        }
    }
}

impl TrainFile {
    /// A preset by name.
    pub fn preset(name: &str) -> Result<Self, ConfigError> {
        let (_, text) =
            PRESETS
                .iter()
                .find(|(n, _)| *n == name)
                .ok_or_else(|| ConfigError::Invalid {
                    field: "preset".into(),
                    reason: format!(
                        "unknown preset `{name}`: use {}",
                        PRESETS.map(|(n, _)| format!("`{n}`")).join(" or ")
                    ),
                })?;
        let file: Self = toml::from_str(text)
            .map_err(|e| ConfigError::Parse(format!("preset `{name}`: {e}")))?;
        file.validate()?;
        Ok(file)
    }

    /// The validated contents of a train file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let file: Self = read_toml(path)?;
        file.validate()?;
        Ok(file)
    }

    /// Checks every field; the error names the first one out of range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        tweezer_learner::config::validate_tables(&self.env, &self.learner)?;
        if let Some(key) = SET_PER_ACTOR.iter().find(|k| self.actor.contains_key(**k)) {
            return Err(ConfigError::Invalid {
                field: format!("actor.{key}"),
                reason: "is set by `experiment train` for each actor; remove it".into(),
            });
        }
        let actor: ActorConfig = toml::Value::Table(self.actor.clone())
            .try_into()
            .map_err(|e: toml::de::Error| ConfigError::invalid("actor", e.message()))?;
        actor.validate().map_err(|e| e.in_table("actor"))?;
        self.train.validate().map_err(|e| e.in_table("train"))?;
        if !self.sweep.is_empty() {
            self.sweep.runs(self)?;
        }
        Ok(())
    }

    /// The configuration as TOML, every default written out.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("every config field is TOML-representable")
    }
}

impl TrainConfig {
    /// Checks every field; the error names the first one out of range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let invalid = |field: &str, reason: String| {
            Err(ConfigError::Invalid {
                field: field.into(),
                reason,
            })
        };
        if !(1..=64).contains(&self.actors) {
            return invalid("actors", format!("{} is not in 1..=64", self.actors));
        }
        if !(self.minutes.is_finite() && self.minutes >= 0.0) {
            return invalid(
                "minutes",
                "must be finite and >= 0 (0: until stopped)".into(),
            );
        }
        if self.eval_batch == 0 {
            return invalid("eval_batch", "must be at least 1".into());
        }
        if let Err(e) = self.eval_seeds() {
            return invalid("eval_seeds", e.to_string());
        }
        if let Err(e) = self.picture_seeds() {
            return invalid("picture_seeds", e.to_string());
        }
        if let Err(e) = self.validation_seeds() {
            return invalid("validation_seeds", e.to_string());
        }
        Ok(())
    }

    /// The held-out evaluation seeds.
    pub fn eval_seeds(&self) -> Result<Seeds, tweezer_gym::SeedsError> {
        self.eval_seeds.parse()
    }

    /// The validation seeds, if any.
    pub fn validation_seeds(&self) -> Result<Option<Seeds>, tweezer_gym::SeedsError> {
        if self.validation_seeds.trim().is_empty() {
            return Ok(None);
        }
        self.validation_seeds.parse().map(Some)
    }

    /// The seeds drawn as pictures.
    pub fn picture_seeds(&self) -> Result<Seeds, tweezer_gym::SeedsError> {
        self.picture_seeds.parse()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tweezer_learner::config::DeviceChoice;

    #[test]
    fn presets_are_valid_and_differ() {
        let paper = TrainFile::preset("paper").unwrap();
        let quick = TrainFile::preset("quick").unwrap();
        assert_eq!(paper.env, EnvConfig::default());
        assert_ne!(quick.env.image, paper.env.image);
        assert!(quick.train.minutes > 0.0);
        let err = TrainFile::preset("fast").unwrap_err().to_string();
        assert!(err.contains("`paper` or `quick` or `lean`"), "{err}");
        let lean = TrainFile::preset("lean").unwrap();
        assert_eq!(lean.env, EnvConfig::default(), "SPEC's environment");
        assert!(matches!(
            lean.learner.network,
            tweezer_learner::config::NetworkConfig::Set(_)
        ));
    }

    #[test]
    fn a_file_round_trips_and_errors_name_the_field() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("train.toml");
        let quick = TrainFile::preset("quick").unwrap();
        std::fs::write(&path, quick.to_toml()).unwrap();
        assert_eq!(TrainFile::load(&path).unwrap(), quick);
        for (text, field) in [
            ("[train]\nactors = 0\n", "train.actors"),
            ("[train]\neval_seeds = \"9..3\"\n", "train.eval_seeds"),
            ("[train]\npicture_seeds = \"x\"\n", "train.picture_seeds"),
            (
                "[train]\nvalidation_seeds = \"1..\"\n",
                "train.validation_seeds",
            ),
            ("[actor]\nid = \"a\"\n", "actor.id"),
            ("[actor]\nenvz = 4\n", "unknown field `envz`"),
            ("[actor]\nenvs = 0\n", "actor.envs"),
            ("[actor]\ndemonstrators = 99\n", "actor.demonstrators"),
            ("[learner.td3]\ngamma = 2.0\n", "learner.td3.gamma"),
        ] {
            std::fs::write(&path, text).unwrap();
            let err = TrainFile::load(&path).unwrap_err().to_string();
            assert!(err.contains(field), "{text}: {err}");
        }
    }

    /// This binary never opens the learner's device: a GPU device is for
    /// the learner binary it starts to open or refuse, whatever features
    /// this one was built with.
    #[test]
    fn a_gpu_device_is_left_to_the_learner_binary() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("train.toml");
        for (text, device) in [
            ("[learner]\ndevice = \"cuda\"\n", DeviceChoice::Cuda),
            ("[learner]\ndevice = \"wgpu\"\n", DeviceChoice::Wgpu),
        ] {
            std::fs::write(&path, text).unwrap();
            assert_eq!(TrainFile::load(&path).unwrap().learner.device, device);
        }
    }
}
