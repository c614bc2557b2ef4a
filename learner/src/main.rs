//! The learner process: `serve` trains behind the gRPC service, `config`
//! prints the effective configuration, `bench` measures the parts.

use anyhow::bail;
use burn::tensor::Device;
use clap::{Parser, Subcommand};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use tweezer_gym::{Seeds, init_logging};
use tweezer_learner::config::LearnerFile;
use tweezer_learner::report::{self, Report, ReportOptions};
use tweezer_learner::serve::{CONFIG, Start, serve};
use tweezer_learner::train::{self, TrainFile, TrainOptions, TrainOutcome};

/// Tweezer RL learner: FIFO replay, TD3 in Burn, versioned policy snapshots
/// over gRPC.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    /// TOML config file: `[env]` and `[learner]` tables over SPEC defaults.
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
    /// Serve actors and train until SIGINT or SIGTERM, then write a final
    /// checkpoint.
    Serve {
        /// Continue the run in DIR from its newest valid checkpoint (its
        /// config.toml unless --config is given).
        #[arg(long, value_name = "DIR")]
        resume: Option<PathBuf>,
        /// Listen here instead of `learner.listen` (port 0: any free port).
        #[arg(long, value_name = "ADDR")]
        listen: Option<SocketAddr>,
        /// Serve Prometheus metrics here instead of at
        /// `learner.metrics_listen`.
        #[arg(long, value_name = "ADDR")]
        metrics_listen: Option<SocketAddr>,
        /// Write the run here instead of `learner.run_dir`.
        #[arg(long, value_name = "DIR", conflicts_with = "resume")]
        run_dir: Option<PathBuf>,
        /// Continue the run directory's run from its newest valid
        /// checkpoint if it has checkpoints, start it otherwise (for
        /// restarts by systemd, Slurm or Kubernetes).
        #[arg(long, conflicts_with = "resume")]
        auto_resume: bool,
        /// The security file: certificate, key, accepted tokens (see the
        /// README's Security section).
        #[arg(long, env = tweezer_rpc::SECURITY_ENV, value_name = "FILE")]
        security: Option<PathBuf>,
    },
    /// Train an agent in one command: the learner and its actors as local
    /// processes, a progress bar, a run directory, and at the end the best
    /// snapshot evaluated on held-out seeds with the paper's figures.
    /// `--config` names a train file (`[env]`, `[learner]`, `[actor]`,
    /// `[train]`) instead of a preset.
    Train {
        /// `quick` (learns on a 2-core laptop in 30 minutes) or `paper`
        /// (SPEC settings; for a GPU or a cluster).
        #[arg(long, conflicts_with = "config")]
        preset: Option<String>,
        /// Minutes of training (0: until Ctrl-C) instead of `train.minutes`.
        #[arg(long)]
        minutes: Option<f64>,
        /// Actor processes instead of `train.actors`.
        #[arg(long)]
        actors: Option<usize>,
        /// The run directory (default: the first free `runs/<preset>-<n>`).
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
        /// Continue the run in --out from its newest checkpoint.
        #[arg(long, requires = "out", conflicts_with_all = ["preset", "config", "actors"])]
        resume: bool,
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
    /// with one label averaged), each run's best snapshot against greedy on
    /// held-out seeds, Figs. 5 and 6 of the best.
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
    /// Print the effective configuration (the file over SPEC defaults) as TOML.
    Config,
    /// Measure TD3 updates, inference and replay memory on the CPU.
    Bench {
        /// TD3 updates timed (rounded up to an even number).
        #[arg(long, default_value_t = 4)]
        updates: usize,
        /// Replay capacity filled to measure bytes per transition.
        #[arg(long, default_value_t = 1_050_000)]
        replay_capacity: usize,
        /// Print one JSON object instead of a table.
        #[arg(long)]
        json: bool,
    },
}

/// mimalloc keeps freed pages for reuse: a TD3 update allocates and frees
/// hundreds of megabytes of tensors, and with glibc's malloc the pages of
/// each were faulted in afresh (an update took 2.0 s instead of 1.6 s).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    init_logging(cli.log_json);
    match cli.command {
        Command::Serve {
            resume,
            listen,
            metrics_listen,
            run_dir,
            auto_resume,
            security,
        } => {
            let path = match (&cli.config, &resume) {
                (Some(path), _) => Some(path.clone()),
                (None, Some(dir)) => Some(dir.join(CONFIG)),
                (None, None) => None,
            };
            let mut file = LearnerFile::load(path.as_deref())?;
            if let Some(dir) = resume.clone().or(run_dir) {
                file.learner.run_dir = dir;
            }
            if let Some(addr) = listen {
                file.learner.listen = addr;
            }
            if metrics_listen.is_some() {
                file.learner.metrics_listen = metrics_listen;
            }
            let security = tweezer_rpc::Security::load(security.as_deref())?;
            let start = match (&resume, auto_resume) {
                (Some(_), _) => Start::Resume,
                (None, true) => Start::Auto,
                (None, false) => Start::Fresh,
            };
            serve(file, start, &security)?;
        }
        Command::Train {
            preset,
            minutes,
            actors,
            out,
            resume,
            actor_bin,
            print_config,
            json,
        } => {
            let (mut file, name) = match (&cli.config, preset) {
                (Some(path), _) => (TrainFile::load(path)?, file_stem(path)),
                (None, preset) => {
                    let name = preset.unwrap_or_else(|| "quick".into());
                    (TrainFile::preset(&name)?, name)
                }
            };
            if let Some(actors) = actors {
                file.train.actors = actors;
            }
            if let Some(minutes) = minutes {
                file.train.minutes = minutes;
            }
            file.validate()?;
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
        Command::Config => print!("{}", LearnerFile::load(cli.config.as_deref())?.to_toml()),
        Command::Bench {
            updates,
            replay_capacity,
            json,
        } => {
            if replay_capacity == 0 {
                bail!("--replay-capacity must be at least 1");
            }
            let config = LearnerFile::load(cli.config.as_deref())?;
            let report = tweezer_learner::bench::run(
                &config.env,
                config.learner.batch_size,
                replay_capacity,
                updates,
                &Device::flex(),
            )?;
            if json {
                println!("{}", serde_json::to_string(&report)?);
            } else {
                println!(
                    "TD3 update, batch {:<6}  {:.0} ms",
                    report.batch_size, report.update_ms_mean
                );
                println!("  critic step            {:.0} ms", report.critic_step_ms);
                println!("  actor step             {:.0} ms", report.actor_step_ms);
                println!(
                    "actor inference, b1      {:.1} ms",
                    report.actor_infer_ms_batch1
                );
                println!(
                    "actor inference, b16     {:.1} ms",
                    report.actor_infer_ms_batch16
                );
                println!(
                    "replay                   {:.0} bytes/transition at {} transitions",
                    report.replay_bytes_per_transition, report.replay_capacity
                );
                println!(
                    "gRPC ingest, 8 streams   {:.0} transitions/s (TLS, tokens)",
                    report.ingest_transitions_per_sec
                );
                println!(
                    "  plaintext, tokens      {:.0} transitions/s",
                    report.ingest_plaintext_transitions_per_sec
                );
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
