//! The experiment runner: `train` trains an agent with the learner and its
//! actors as local processes, `report` draws and evaluates finished runs.

use anyhow::bail;
use clap::{Parser, Subcommand};
use std::path::{Path, PathBuf};
use tweezer_experiment::report::{self, Report, ReportOptions};
use tweezer_experiment::train::{self, TrainOptions, TrainOutcome};
use tweezer_experiment::train_file::TrainFile;
use tweezer_gym::Seeds;
use tweezer_process::init_logging;

/// Tweezer RL experiments: train an agent in one command, report on runs.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    /// A train file (`[env]`, `[learner]`, `[actor]`, `[train]`, optionally
    /// `[sweep]`) instead of a preset.
    #[arg(long, global = true, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Log as JSON lines (for log collectors) instead of text.
    #[arg(long, global = true)]
    log_json: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Train an agent in one command: the learner and its actors as local
    /// processes, a progress bar, a run directory, and at the end the best
    /// snapshot evaluated on held-out seeds with the paper's figures.
    /// `--config` names a train file (`[env]`, `[learner]`, `[actor]`,
    /// `[train]`) instead of a preset.
    Train {
        /// `lean` (the default: the set network at the full field of view,
        /// the best on a 2-core laptop), `quick` (the paper's CNN at
        /// 40 x 32, for a 2-core laptop) or `paper` (the settings of
        /// `docs/spec.md`; for a GPU or a cluster).
        #[arg(long, conflicts_with = "config")]
        preset: Option<String>,
        /// Minutes of training (0: until Ctrl-C) instead of `train.minutes`.
        #[arg(long, allow_negative_numbers = true)]
        minutes: Option<f64>,
        /// Actor processes instead of `train.actors`.
        #[arg(long)]
        actors: Option<usize>,
        /// Stop once the learner has made this many updates (its
        /// `learner.max_updates`), or when the minutes run out, whichever
        /// comes first: a policy judged at a number of updates, whatever
        /// the machine's speed.
        #[arg(long, conflicts_with = "resume")]
        updates: Option<u64>,
        /// The run directory (default: the first free `runs/<preset>-<n>`).
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
        /// Continue the run in --out from its newest checkpoint.
        #[arg(long, requires = "out", conflicts_with_all = ["preset", "config", "actors"])]
        resume: bool,
        /// The learner binary, if not next to this one.
        #[arg(long, value_name = "FILE")]
        learner_bin: Option<PathBuf>,
        /// The actor binary, if not next to this one.
        #[arg(long, value_name = "FILE")]
        actor_bin: Option<PathBuf>,
        /// Print the effective train file as TOML and exit.
        #[arg(long)]
        print_config: bool,
        /// Print the summary as one JSON object.
        #[arg(long)]
        json: bool,
    },
    /// Figures and an evaluation table for run directories: Fig. 4 (runs
    /// with one label averaged), each run's best snapshot against greedy
    /// and the planner on held-out seeds, Figs. 5 and 6 of the best.
    Report {
        /// Run directories.
        #[arg(required = true, value_name = "RUN_DIR")]
        runs: Vec<PathBuf>,
        /// Where the figures and tables go.
        #[arg(long, value_name = "DIR", default_value = "report")]
        out: PathBuf,
        /// Held-out episode seeds.
        #[arg(long, default_value = "100000..100200")]
        seeds: Seeds,
        /// Episode seeds drawn as Figs. 5 (each) and 6 (the first).
        #[arg(long, default_value = "100000..100003")]
        picture_seeds: Seeds,
        /// Choose each run's snapshot among its kept ones by success on
        /// these seeds (keep them apart from --seeds) instead of taking the
        /// one published at the best rolling return.
        #[arg(long)]
        validation_seeds: Option<Seeds>,
        /// Episodes evaluated side by side.
        #[arg(long, default_value_t = 64)]
        batch: usize,
        /// Print the report as JSON instead of the table.
        #[arg(long)]
        json: bool,
    },
}

/// mimalloc keeps freed pages for reuse: the report evaluates networks,
/// which allocate and free many tensors.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> std::process::ExitCode {
    tweezer_process::exit_status(run())
}

fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    init_logging(cli.log_json);
    match cli.command {
        Command::Train {
            preset,
            minutes,
            actors,
            updates,
            out,
            resume,
            learner_bin,
            actor_bin,
            print_config,
            json,
        } => {
            let (mut file, name) = match (&cli.config, preset) {
                (Some(path), _) => (TrainFile::load(path)?, file_stem(path)),
                (None, preset) => {
                    let name = preset.unwrap_or_else(|| "lean".into());
                    (TrainFile::preset(&name)?, name)
                }
            };
            if let Some(actors) = actors {
                file.train.actors = actors;
            }
            if let Some(minutes) = minutes {
                file.train.minutes = minutes;
            }
            if let Some(updates) = updates {
                file.learner.max_updates = updates;
            }
            file.validate().map_err(|e| match e {
                // A value given on the command line is blamed on its flag.
                tweezer_config::ConfigError::Invalid { field, reason }
                    if (field == "train.actors" && actors.is_some())
                        || (field == "train.minutes" && minutes.is_some()) =>
                {
                    let flag = field.trim_start_matches("train.");
                    anyhow::anyhow!("--{flag}: {reason}")
                }
                other => other.into(),
            })?;
            if print_config {
                print!("{}", file.to_toml());
                return Ok(());
            }
            let out = match out {
                Some(out) => out,
                None => free_run_dir(&name),
            };
            let outcome = train::run(TrainOptions {
                file,
                out,
                resume,
                minutes,
                learner_bin,
                actor_bin,
            })?;
            print_train_outcome(&outcome, json)?;
        }
        Command::Report {
            runs,
            out,
            seeds,
            picture_seeds,
            validation_seeds,
            batch,
            json,
        } => {
            if let Some(config) = &cli.config {
                bail!(
                    "report reads each run's own train.toml: --config {} does not apply to it (drop it)",
                    config.display()
                );
            }
            if batch == 0 {
                bail!("--batch must be at least 1");
            }
            let options = ReportOptions {
                seeds: seeds.0,
                picture_seeds: picture_seeds.0,
                validation_seeds: validation_seeds.map(|s| s.0),
                batch,
            };
            let report = report::write(&runs, &out, &options)?;
            if json {
                println!("{}", serde_json::to_string(&report)?);
            } else {
                print_report(&report)?;
            }
        }
    }
    Ok(())
}

/// A config file's name without its extension.
fn file_stem(path: &Path) -> String {
    path.file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "run".into())
}

/// The first `runs/<name>-<n>` that does not exist yet.
fn free_run_dir(name: &str) -> PathBuf {
    (1..)
        .map(|n| PathBuf::from("runs").join(format!("{name}-{n}")))
        .find(|dir| !dir.exists())
        .expect("some run directory name is free")
}

fn print_report(report: &Report) -> anyhow::Result<()> {
    let table = report
        .files
        .iter()
        .find(|f| f.extension().is_some_and(|e| e == "md"))
        .map(std::fs::read_to_string)
        .transpose()?
        .unwrap_or_default();
    print!("{table}");
    for file in &report.files {
        println!("wrote {}", file.display());
    }
    Ok(())
}

fn print_train_outcome(outcome: &TrainOutcome, json: bool) -> anyhow::Result<()> {
    if json {
        println!("{}", serde_json::to_string(outcome)?);
        return Ok(());
    }
    for run in &outcome.runs {
        println!(
            "{}: {} steps and {} updates in {:.0} s ({:.1} steps/s, {:.1} updates/s){}",
            run.run_dir.display(),
            run.steps,
            run.updates,
            run.seconds,
            run.end_to_end_steps_per_sec,
            run.updates_per_sec,
            if run.interrupted { ", interrupted" } else { "" }
        );
    }
    if let Some(report) = &outcome.report {
        print_report(report)?;
    }
    Ok(())
}
