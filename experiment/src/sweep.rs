//! Sweeps: a train file's `[sweep]` table names values to try — discount
//! factors, resolutions, reward components switched off, seeds — and the
//! runner trains every combination, one after another (the paper's
//! Fig. 4 b–d). Runs that differ only in seed share a label, so the report
//! averages them.

use crate::train_file::TrainFile;
use serde::{Deserialize, Serialize};
use tweezer_config::ConfigError;
use tweezer_gym::{ImageConfig, RewardComponent};

/// Values to sweep; an empty list leaves the setting as the file has it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SweepConfig {
    /// `learner.seed` values (each run's actors derive their seeds from it).
    pub seeds: Vec<u64>,
    /// `learner.td3.gamma` values.
    pub gamma: Vec<f64>,
    /// `env.image` resolutions, `[width, height]`.
    pub image: Vec<[u32; 2]>,
    /// `env.rewards.off` lists.
    pub rewards_off: Vec<Vec<RewardComponent>>,
}

/// One run of a sweep.
#[derive(Clone, Debug, PartialEq)]
pub struct SweepRun {
    /// The run's directory name inside the sweep's.
    pub name: String,
    /// Its train file: the sweep's with this run's values, no `[sweep]`.
    pub file: TrainFile,
}

/// One swept value.
#[derive(Clone, Debug)]
enum Change {
    Gamma(f64),
    Image([u32; 2]),
    RewardsOff(Vec<RewardComponent>),
}

impl Change {
    fn apply(&self, file: &mut TrainFile) {
        match self {
            Self::Gamma(g) => file.learner.td3.gamma = *g,
            Self::Image([width, height]) => {
                file.env.image = ImageConfig {
                    width: *width,
                    height: *height,
                }
            }
            Self::RewardsOff(off) => file.env.rewards.off = off.clone(),
        }
    }

    fn label(&self) -> String {
        match self {
            Self::Gamma(g) => format!("gamma {g}"),
            Self::Image([w, h]) => format!("image {w}x{h}"),
            Self::RewardsOff(off) if off.is_empty() => "all rewards".into(),
            Self::RewardsOff(off) => {
                let names: Vec<String> = off
                    .iter()
                    .map(|c| format!("{c:?}").to_lowercase())
                    .collect();
                format!("no {}", names.join("+"))
            }
        }
    }
}

impl SweepConfig {
    /// Whether the table asks for anything.
    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }

    /// Every combination of the swept values applied to `base`, seeds
    /// innermost; each run validated.
    pub fn runs(&self, base: &TrainFile) -> Result<Vec<SweepRun>, ConfigError> {
        let axes: [Vec<Change>; 3] = [
            self.gamma.iter().map(|&g| Change::Gamma(g)).collect(),
            self.image.iter().map(|&i| Change::Image(i)).collect(),
            self.rewards_off
                .iter()
                .map(|off| Change::RewardsOff(off.clone()))
                .collect(),
        ];
        let mut settings: Vec<Vec<&Change>> = vec![Vec::new()];
        for axis in axes.iter().filter(|a| !a.is_empty()) {
            settings = settings
                .iter()
                .flat_map(|changes| {
                    axis.iter().map(move |change| {
                        let mut changes = changes.clone();
                        changes.push(change);
                        changes
                    })
                })
                .collect();
        }
        let seeds = if self.seeds.is_empty() {
            vec![base.learner.seed]
        } else {
            self.seeds.clone()
        };
        let mut runs = Vec::new();
        for changes in settings {
            let label = if changes.is_empty() {
                base.train.label.clone()
            } else {
                let labels: Vec<String> = changes.iter().map(|c| c.label()).collect();
                labels.join(", ")
            };
            for &seed in &seeds {
                let mut file = base.clone();
                for change in &changes {
                    change.apply(&mut file);
                }
                file.learner.seed = seed;
                file.train.label = label.clone();
                file.sweep = SweepConfig::default();
                file.validate().map_err(|e| match e {
                    ConfigError::Invalid { field, reason } => ConfigError::Invalid {
                        field,
                        reason: format!("{reason} (in sweep run `{label}`, seed {seed})"),
                    },
                    other => other,
                })?;
                runs.push(SweepRun {
                    name: format!("{}seed{seed}", slug(&label)),
                    file,
                });
            }
        }
        Ok(runs)
    }
}

/// A label as a directory name prefix: `gamma 0.9, image 80x64` →
/// `gamma0.9_image80x64-`.
fn slug(label: &str) -> String {
    let mut slug: String = label
        .chars()
        .filter_map(|c| match c {
            ',' => Some('_'),
            ' ' => None,
            '+' | '-' | '.' | '_' => Some(c),
            c if c.is_ascii_alphanumeric() => Some(c),
            _ => None,
        })
        .collect();
    if !slug.is_empty() {
        slug.push('-');
    }
    slug
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_combination_with_seeds_innermost() {
        let base = TrainFile::preset("quick").unwrap();
        let sweep = SweepConfig {
            seeds: vec![1, 2],
            gamma: vec![0.8, 0.99],
            image: vec![[40, 32], [80, 64]],
            rewards_off: vec![vec![], vec![RewardComponent::Time, RewardComponent::Carry]],
        };
        let runs = sweep.runs(&base).unwrap();
        assert_eq!(runs.len(), 16);
        assert_eq!(
            runs[0].file.train.label,
            "gamma 0.8, image 40x32, all rewards"
        );
        assert_eq!(runs[0].name, "gamma0.8_image40x32_allrewards-seed1");
        assert_eq!(runs[1].file.learner.seed, 2);
        assert_eq!(runs[1].file.train.label, runs[0].file.train.label);
        let last = &runs[15];
        assert_eq!(
            last.file.train.label,
            "gamma 0.99, image 80x64, no time+carry"
        );
        assert_eq!(
            last.file.env.image,
            ImageConfig {
                width: 80,
                height: 64
            }
        );
        assert_eq!(last.file.learner.td3.gamma, 0.99);
        assert!(last.file.sweep.is_empty());
        let names: std::collections::HashSet<_> = runs.iter().map(|r| &r.name).collect();
        assert_eq!(names.len(), 16, "distinct directories");
    }

    #[test]
    fn an_invalid_value_names_the_run() {
        let base = TrainFile::preset("quick").unwrap();
        for (image, run, reason) in [
            ([40, 40], "image 40x40", "env.image"),
            ([5, 4], "image 5x4", "too small for the paper network"),
        ] {
            let sweep = SweepConfig {
                image: vec![image],
                ..Default::default()
            };
            let err = sweep.runs(&base).unwrap_err().to_string();
            assert!(err.contains(run) && err.contains(reason), "{err}");
        }
    }
}
