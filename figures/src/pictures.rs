//! A policy's episodes drawn as the paper's Fig. 5 (one per seed) and Fig. 6
//! (twelve targets from the first seed, under identical free-sphere motion).

use crate::FigureError;
use crate::scenes::{episode_figure, targets_figure};
use std::path::{Path, PathBuf};
use tweezer_gym::{EnvConfig, EpisodeStats, EvalSummary, Policy, Target, Trajectory, record};

/// Targets in the Fig. 6 picture, evenly spaced around the start.
const FIG6_TARGETS: u32 = 12;

/// What [`draw_episodes`] wrote, and how the drawn Fig. 5 episodes went.
#[derive(Clone, Debug)]
pub struct Pictures {
    /// The files written, Fig. 5 pictures first.
    pub written: Vec<PathBuf>,
    /// The Fig. 5 episodes' summary.
    pub summary: EvalSummary,
}

/// Records `policy` on `seeds` and writes `fig5-seed<S>.png` for each and
/// `fig6-seed<S>.png` for the first into `out`.
pub fn draw_episodes(
    config: &EnvConfig,
    policy: &mut dyn Policy,
    seeds: &[u64],
    out: &Path,
) -> Result<Pictures, FigureError> {
    std::fs::create_dir_all(out).map_err(|e| FigureError::Directory {
        path: out.display().to_string(),
        reason: e.to_string(),
    })?;
    let mut written = Vec::new();
    let mut episodes = Vec::new();
    for &seed in seeds {
        let trajectory = record(config, seed, Target::Random, policy)?;
        let path = out.join(format!("fig5-seed{seed}.png"));
        episode_figure(&trajectory, &path)?;
        written.push(path);
        episodes.push(stats(&trajectory));
    }
    if let Some(&seed) = seeds.first() {
        let twelve = (0..FIG6_TARGETS)
            .map(|k| {
                let angle = f64::from(k) * std::f64::consts::TAU / f64::from(FIG6_TARGETS);
                record(config, seed, Target::Angle(angle), policy)
            })
            .collect::<Result<Vec<Trajectory>, _>>()?;
        let path = out.join(format!("fig6-seed{seed}.png"));
        targets_figure(&twelve, &path)?;
        written.push(path);
    }
    Ok(Pictures {
        written,
        summary: EvalSummary::of(&episodes),
    })
}

fn stats(t: &Trajectory) -> EpisodeStats {
    EpisodeStats {
        seed: t.seed,
        episode_return: t.episode_return,
        steps: t.actions.len() as u32,
        outcome: t.outcome,
    }
}
