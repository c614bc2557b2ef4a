//! `experiment report`: the paper's figures and an evaluation table for one or
//! more run directories. Runs with the same label (a sweep's seeds) are
//! averaged in Fig. 4; each run's snapshot — the best of its kept ones on
//! validation seeds, or the one published at its best rolling return — is
//! evaluated on held-out seeds next to the greedy and planner baselines;
//! the best of them is drawn (Figs. 5, 6). The evaluated snapshot is kept
//! as the run's `snapshots/chosen.safetensors`.

use crate::train_file::TrainFile;
use anyhow::Context;
use burn::tensor::Device;
use serde::Serialize;
use std::io::BufRead;
use std::path::{Path, PathBuf};
use tweezer_figures::{Curve, RewardFigure, draw_episodes, reward_figure};
use tweezer_gym::{Baseline, EnvConfig, EvalSummary, evaluate};
use tweezer_learner::config::LearnerFile;
use tweezer_learner::persistence::durable_write::write_atomic;
use tweezer_learner::persistence::run_dir::RunDir;
use tweezer_nets::{NetworkPolicy, without_critics};

/// Episodes in Fig. 4's rolling mean (the paper's).
pub const WINDOW: usize = 100;

/// What to evaluate and draw.
#[derive(Clone, Debug)]
pub struct ReportOptions {
    /// Held-out episode seeds for the table.
    pub seeds: Vec<u64>,
    /// Episode seeds drawn as Figs. 5 and 6.
    pub picture_seeds: Vec<u64>,
    /// Seeds, apart from the held-out ones, on which each run's kept
    /// snapshots are compared to choose the one reported; none: `best`.
    pub validation_seeds: Option<Vec<u64>>,
    /// Episodes evaluated side by side.
    pub batch: usize,
}

/// One row of the evaluation table.
#[derive(Clone, Debug, Serialize)]
pub struct EvalRow {
    /// The setting.
    pub label: String,
    /// The run directory (empty for a baseline).
    pub run: String,
    /// `v<N>`, `greedy` or `planner`.
    pub policy: String,
    /// How the snapshot was chosen (empty for a baseline).
    pub chosen_by: String,
    /// The snapshot file.
    pub snapshot: String,
    /// The rates and means.
    #[serde(flatten)]
    pub summary: EvalSummary,
}

/// The report's JSON file.
#[derive(Debug, Serialize)]
pub struct Report {
    /// Episode seeds of the table.
    pub seeds: String,
    /// Rows: each run's best snapshot, then greedy and the planner per
    /// environment.
    pub rows: Vec<EvalRow>,
    /// Theoretical maximum return per label.
    pub ideal_return: Vec<(String, f64)>,
    /// The files written.
    pub files: Vec<PathBuf>,
}

/// A run directory, read.
struct Run {
    dir: PathBuf,
    label: String,
    env: EnvConfig,
    returns: Vec<f64>,
}

impl Run {
    fn read(dir: &Path) -> anyhow::Result<Self> {
        let run = RunDir::new(dir);
        let config = LearnerFile::of_run(dir)?;
        let label = run_label(dir)?;
        let returns = episode_returns(&run.run_log())?;
        Ok(Self {
            dir: dir.to_path_buf(),
            label,
            env: config.env,
            returns,
        })
    }

    /// The snapshot files to choose from: `best` first, then the kept
    /// versions, newest first.
    fn candidates(&self) -> anyhow::Result<Vec<PathBuf>> {
        let run = RunDir::new(&self.dir);
        let dir = run.snapshots();
        let best = run.best_snapshot();
        if !best.is_file() {
            return Ok(Vec::new());
        }
        let mut versions: Vec<PathBuf> = std::fs::read_dir(&dir)
            .with_context(|| format!("cannot list {}", dir.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with('v') && n.ends_with(".safetensors"))
            })
            .collect();
        versions.sort_unstable_by(|a, b| b.cmp(a));
        Ok(std::iter::once(best).chain(versions).collect())
    }

    /// The policy to report: with `validation` seeds, the candidate and
    /// the way of acting (its actor alone, or checked by its critics where
    /// it has them) with the highest success rate (then return) on them,
    /// since that way is what ships, and a snapshot's rank alone is a poor
    /// guide to its rank checked; else `best`, as it is.
    fn choose(
        &self,
        validation: Option<&[u64]>,
        batch: usize,
        device: &Device,
    ) -> anyhow::Result<Option<Chosen>> {
        let candidates = self.candidates()?;
        let Some(validation) = validation else {
            let Some(path) = candidates.first() else {
                return Ok(None);
            };
            let (policy, info) = NetworkPolicy::from_file(path, &self.env, device)?;
            return Ok(Some(Chosen {
                path: path.clone(),
                how: "best rolling return".into(),
                dropped_check: false,
                policy,
                version: info.version,
            }));
        };
        let mut chosen: Option<Validated> = None;
        let mut seen = Vec::new();
        for path in &candidates {
            let (policy, info) = NetworkPolicy::from_file(path, &self.env, device)?;
            if seen.contains(&info.version) {
                continue;
            }
            seen.push(info.version);
            let validated = Validated::of(
                path,
                policy,
                info.version,
                &self.env,
                validation,
                batch,
                device,
            )?;
            tracing::info!(
                run = %self.dir.display(),
                version = info.version,
                alone = validated.alone.success_rate,
                checked = validated.checked.as_ref().map(|c| c.success_rate),
                "validated"
            );
            if chosen
                .as_ref()
                .is_none_or(|b| better(validated.score(), b.score()))
            {
                chosen = Some(validated);
            }
        }
        let Some(Validated {
            chosen,
            alone,
            checked,
        }) = chosen
        else {
            return Ok(None);
        };
        let mut how = format!(
            "best of {} on validation seeds {}",
            seen.len(),
            describe_seeds(validation)
        );
        if let Some(checked) = checked {
            how += &format!(
                ", critics' check {} there ({:.3} against {:.3} alone)",
                if chosen.dropped_check {
                    "dropped"
                } else {
                    "kept"
                },
                checked.success_rate,
                alone.success_rate
            );
        }
        Ok(Some(Chosen { how, ..chosen }))
    }
}

/// A candidate snapshot in its better way of acting, with its figures on
/// the validation seeds both ways.
struct Validated {
    chosen: Chosen,
    alone: EvalSummary,
    /// Checked by its critics; none for a snapshot without them.
    checked: Option<EvalSummary>,
}

impl Validated {
    /// Evaluates the snapshot at `path` on `validation`, alone and, where
    /// it has critics, checked; the check is kept only where it does better.
    fn of(
        path: &Path,
        policy: NetworkPolicy,
        version: u64,
        env: &EnvConfig,
        validation: &[u64],
        batch: usize,
        device: &Device,
    ) -> anyhow::Result<Self> {
        let mut summary = |p: &mut NetworkPolicy| {
            evaluate(env, p, validation, batch).map(|e| EvalSummary::of(&e))
        };
        let (mut alone_policy, mut checked_policy) = if policy.has_critics() {
            let (copy, _) = NetworkPolicy::from_file(path, env, device)?;
            (copy.actor_alone(), Some(policy))
        } else {
            (policy, None)
        };
        let alone = summary(&mut alone_policy)?;
        let checked = checked_policy.as_mut().map(&mut summary).transpose()?;
        let keep = checked.as_ref().is_some_and(|c| better(c, &alone));
        let policy = match checked_policy {
            Some(checked) if keep => checked,
            _ => alone_policy,
        };
        Ok(Self {
            chosen: Chosen {
                path: path.to_path_buf(),
                how: String::new(),
                dropped_check: checked.is_some() && !keep,
                policy,
                version,
            },
            alone,
            checked,
        })
    }

    /// Its figures in its better way of acting.
    fn score(&self) -> &EvalSummary {
        match &self.checked {
            Some(checked) if !self.chosen.dropped_check => checked,
            _ => &self.alone,
        }
    }
}

/// The snapshot a run is reported with, loaded, and how it was chosen.
struct Chosen {
    path: PathBuf,
    how: String,
    /// Whether the snapshot's critics were found to check its actor worse
    /// than it acts alone, and so dropped.
    dropped_check: bool,
    policy: NetworkPolicy,
    version: u64,
}

/// Copies the reported snapshot to the run's `snapshots/chosen.safetensors`
/// (atomically: a reader sees the old copy or the new one), so that the
/// file the table quotes has a name that outlives the learner's pruning;
/// without its critics where the report dropped their check, so that the
/// microscope acts as reported.
fn keep_chosen(run: &Path, chosen: &Chosen) -> anyhow::Result<PathBuf> {
    let copy = RunDir::new(run).chosen_snapshot();
    let failed = || {
        format!(
            "cannot copy {} to {}",
            chosen.path.display(),
            copy.display()
        )
    };
    let mut bytes = std::fs::read(&chosen.path).with_context(failed)?;
    if chosen.dropped_check {
        bytes = without_critics(&bytes).with_context(failed)?;
    }
    write_atomic(&copy, |w| w.write_all(&bytes)).with_context(failed)?;
    Ok(copy)
}

/// The run's label from its train file, or the directory's name.
fn run_label(dir: &Path) -> anyhow::Result<String> {
    let path = RunDir::new(dir).train_file();
    if path.is_file() {
        let train = TrainFile::load(&path)?;
        if !train.train.label.is_empty() {
            return Ok(train.train.label);
        }
    }
    let name = std::fs::canonicalize(dir)
        .ok()
        .and_then(|d| d.file_name().map(|n| n.to_string_lossy().into_owned()));
    Ok(name.unwrap_or_else(|| dir.display().to_string()))
}

/// Every episode's return from a metrics file, in order. A torn last line
/// (a learner killed mid-write) is skipped.
fn episode_returns(path: &Path) -> anyhow::Result<Vec<f64>> {
    let file =
        std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let mut returns = Vec::new();
    for (number, line) in std::io::BufReader::new(file).lines().enumerate() {
        let line = line.with_context(|| format!("cannot read {}", path.display()))?;
        let Ok(value) = serde_json::from_str::<serde_json::Value>(&line) else {
            tracing::warn!(path = %path.display(), line = number + 1, "skipping an unreadable metrics line");
            continue;
        };
        if value["kind"] == "episode"
            && let Some(r) = value["episode_return"].as_f64()
        {
            returns.push(r);
        }
    }
    Ok(returns)
}

/// Writes Fig. 4 (`fig4-reward.svg`), the evaluation table (`eval.md`,
/// `eval.json`) and Figs. 5 and 6 of the best run's best snapshot into `out`.
pub fn write(runs: &[PathBuf], out: &Path, options: &ReportOptions) -> anyhow::Result<Report> {
    anyhow::ensure!(!runs.is_empty(), "no run directory to report on");
    let runs = runs
        .iter()
        .map(|d| Run::read(d))
        .collect::<anyhow::Result<Vec<_>>>()?;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let mut files = Vec::new();
    let ideal = draw_rewards(&runs, out, &mut files)?;
    let mut rows = Vec::new();
    let best = evaluate_runs(&runs, options, &mut rows, &mut files)?;
    rows.extend(baseline_rows(&runs, options)?);
    if let Some((k, mut policy)) = best {
        let run = &runs[k];
        let pictures = draw_episodes(&run.env, &mut policy, &options.picture_seeds, out)?;
        files.extend(pictures.written);
    }

    let seeds = describe_seeds(&options.seeds);
    let md = out.join("eval.md");
    let straight = (runs[0].env.ideal_steps(), runs[0].env.ideal_return());
    std::fs::write(&md, markdown(&rows, &seeds, straight))
        .with_context(|| format!("cannot write {}", md.display()))?;
    files.push(md);
    let json = out.join("eval.json");
    files.push(json.clone());
    let report = Report {
        seeds,
        rows,
        ideal_return: ideal,
        files,
    };
    std::fs::write(&json, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("cannot write {}", json.display()))?;
    Ok(report)
}

/// Draws Fig. 4 into `out` (listed in `files`): one curve per label over
/// its runs, with each label's ideal return dashed in its colour (once,
/// in black, when all are equal); returns the ideal return of each label.
fn draw_rewards(
    runs: &[Run],
    out: &Path,
    files: &mut Vec<PathBuf>,
) -> anyhow::Result<Vec<(String, f64)>> {
    let mut curves: Vec<Curve> = Vec::new();
    let mut ideal: Vec<(String, f64)> = Vec::new();
    for run in runs {
        match curves.iter_mut().find(|c| c.label == run.label) {
            Some(curve) => curve.runs.push(run.returns.clone()),
            None => {
                curves.push(Curve {
                    label: run.label.clone(),
                    runs: vec![run.returns.clone()],
                });
                ideal.push((run.label.clone(), run.env.ideal_return()));
            }
        }
    }
    let fig4 = out.join("fig4-reward.svg");
    let all_equal = ideal.windows(2).all(|w| (w[0].1 - w[1].1).abs() < 1e-9);
    let dashed = if all_equal {
        vec![(String::new(), ideal[0].1)]
    } else {
        ideal.iter().map(|(l, v)| (format!(" ({l})"), *v)).collect()
    };
    let figure = RewardFigure {
        title: "Reward per episode".into(),
        window: WINDOW,
        ideal: dashed,
    };
    match reward_figure(&curves, &figure, &fig4) {
        Ok(()) => files.push(fig4),
        Err(tweezer_figures::FigureError::Empty) => {
            tracing::warn!("no episode finished in any run: no Fig. 4");
        }
        Err(e) => return Err(e.into()),
    }
    Ok(ideal)
}

/// Evaluates each run's chosen snapshot on the held-out seeds into `rows`
/// (its copy kept as `chosen.safetensors` and listed in `files`); returns
/// the run whose snapshot did best, with that policy.
fn evaluate_runs(
    runs: &[Run],
    options: &ReportOptions,
    rows: &mut Vec<EvalRow>,
    files: &mut Vec<PathBuf>,
) -> anyhow::Result<Option<(usize, NetworkPolicy)>> {
    let device = Device::flex();
    let mut best: Option<(usize, NetworkPolicy, EvalSummary)> = None;
    for (k, run) in runs.iter().enumerate() {
        let validation = options.validation_seeds.as_deref();
        let Some(mut chosen) = run.choose(validation, options.batch, &device)? else {
            tracing::warn!(run = %run.dir.display(), "no best snapshot yet: not evaluated");
            continue;
        };
        files.push(keep_chosen(&run.dir, &chosen)?);
        let held_out = |policy: &mut NetworkPolicy| -> anyhow::Result<EvalSummary> {
            let episodes = evaluate(&run.env, policy, &options.seeds, options.batch)?;
            Ok(EvalSummary::of(&episodes))
        };
        let summary = held_out(&mut chosen.policy)?;
        let row = |policy: String, summary: EvalSummary| EvalRow {
            label: run.label.clone(),
            run: run.dir.display().to_string(),
            policy,
            chosen_by: chosen.how.clone(),
            snapshot: chosen.path.display().to_string(),
            summary,
        };
        rows.push(row(format!("v{}", chosen.version), summary));
        // The other way to act, to show what the critics' check adds.
        let (other, _) = NetworkPolicy::from_file(&chosen.path, &run.env, &device)?;
        if other.has_critics() {
            let (mut other, name) = if chosen.dropped_check {
                (other, "checked by its critics")
            } else {
                (other.actor_alone(), "actor alone")
            };
            let summary = held_out(&mut other)?;
            rows.push(row(format!("v{} {name}", chosen.version), summary));
        }
        if best.as_ref().is_none_or(|(_, _, b)| better(&summary, b)) {
            best = Some((k, chosen.policy, summary));
        }
    }
    Ok(best.map(|(k, policy, _)| (k, policy)))
}

/// The greedy and planner baselines on the same seeds, once per distinct
/// environment among the runs.
fn baseline_rows(runs: &[Run], options: &ReportOptions) -> anyhow::Result<Vec<EvalRow>> {
    let mut rows = Vec::new();
    let mut baselines: Vec<&EnvConfig> = Vec::new();
    for run in runs {
        if baselines.contains(&&run.env) {
            continue;
        }
        baselines.push(&run.env);
        for baseline in [Baseline::Greedy, Baseline::Planner] {
            let summary = EvalSummary::of(&evaluate(
                &run.env,
                baseline.policy(&run.env).as_mut(),
                &options.seeds,
                options.batch,
            )?);
            rows.push(EvalRow {
                label: run.label.clone(),
                run: String::new(),
                policy: baseline.name().into(),
                chosen_by: String::new(),
                snapshot: String::new(),
                summary,
            });
        }
    }
    Ok(rows)
}

/// Higher success rate first, then higher mean return.
fn better(a: &EvalSummary, b: &EvalSummary) -> bool {
    (a.success_rate, a.mean_return) > (b.success_rate, b.mean_return)
}

/// `100000..100200` for a contiguous list, else the count.
fn describe_seeds(seeds: &[u64]) -> String {
    match (seeds.first(), seeds.last()) {
        (Some(&a), Some(&b)) if seeds.windows(2).all(|w| w[1] == w[0] + 1) => {
            format!("{a}..{}", b + 1)
        }
        _ => format!("{} seeds", seeds.len()),
    }
}

/// The table in Markdown, and the ideal straight run's (steps, return) of
/// the first run's environment.
fn markdown(rows: &[EvalRow], seeds: &str, (steps, ideal): (f64, f64)) -> String {
    let mut md = format!(
        "Evaluation on episode seeds {seeds}\n\n| setting | policy | chosen by | run | episodes | success | collision | timeout | mean return | mean steps | steps to success |\n| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n"
    );
    for r in rows {
        let s = &r.summary;
        md.push_str(&format!(
            "| {} | {} | {} | {} | {} | {:.3} | {:.3} | {:.3} | {:.1} | {:.1} | {} |\n",
            r.label,
            r.policy,
            r.chosen_by,
            r.run,
            s.episodes,
            s.success_rate,
            s.collision_rate,
            s.timeout_rate,
            s.mean_return,
            s.mean_steps,
            s.mean_steps_success
                .map_or_else(|| "—".to_string(), |v| format!("{v:.1}"))
        ));
    }
    md.push_str(&format!(
        "\nThe ideal straight run to the target (mean over target angles, nothing in the way): {steps:.1} steps, return {ideal:.1}.\n"
    ));
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeds_are_described_as_a_range_when_contiguous() {
        assert_eq!(describe_seeds(&[5, 6, 7]), "5..8");
        assert_eq!(describe_seeds(&[5, 7]), "2 seeds");
    }

    #[test]
    fn episode_returns_skip_other_kinds_and_torn_lines() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.jsonl");
        std::fs::write(
            &path,
            "{\"kind\":\"episode\",\"episode_return\":1.5}\n{\"kind\":\"update\",\"updates\":3}\n{\"kind\":\"episode\",\"episode_return\":-2}\n{\"kind\":\"epi",
        )
        .unwrap();
        assert_eq!(episode_returns(&path).unwrap(), vec![1.5, -2.0]);
    }
}
