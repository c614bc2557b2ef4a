//! `actor demo`: the greedy baseline on a few seeds, with the paper's
//! Fig. 5 for each and Fig. 6 for the first.

use anyhow::Context;
use std::path::{Path, PathBuf};
use tweezer_gym::{EnvConfig, EvalSummary, Greedy, Target, Trajectory, record};

/// Targets in the Fig. 6 picture, evenly spaced around the start.
const FIG6_TARGETS: u32 = 12;

/// Records the greedy policy on `seeds`, writes the pictures into `out`, and
/// returns the written paths and the evaluation of those episodes.
pub fn run(
    config: &EnvConfig,
    seeds: &[u64],
    out: &Path,
) -> anyhow::Result<(Vec<PathBuf>, EvalSummary)> {
    std::fs::create_dir_all(out)
        .with_context(|| format!("cannot create output directory {}", out.display()))?;
    let mut written = Vec::new();
    let mut episodes = Vec::new();
    for &seed in seeds {
        let trajectory = record(config, seed, Target::Random, &mut Greedy)?;
        let path = out.join(format!("fig5-seed{seed}.png"));
        tweezer_figures::episode_figure(&trajectory, &path)?;
        written.push(path);
        episodes.push(stats(&trajectory));
    }
    if let Some(&seed) = seeds.first() {
        let twelve = (0..FIG6_TARGETS)
            .map(|k| {
                let angle = f64::from(k) * std::f64::consts::TAU / f64::from(FIG6_TARGETS);
                record(config, seed, Target::Angle(angle), &mut Greedy)
            })
            .collect::<Result<Vec<Trajectory>, _>>()?;
        let path = out.join(format!("fig6-seed{seed}.png"));
        tweezer_figures::targets_figure(&twelve, &path)?;
        written.push(path);
    }
    Ok((written, EvalSummary::of(&episodes)))
}

fn stats(t: &Trajectory) -> tweezer_gym::EpisodeStats {
    tweezer_gym::EpisodeStats {
        seed: t.seed,
        episode_return: t.episode_return,
        steps: t.actions.len() as u32,
        outcome: t.outcome,
    }
}
