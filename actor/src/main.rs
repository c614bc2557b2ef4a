//! The actor process: streams steps to the learner (`run`), evaluates
//! policies, prints a policy's actions, benchmarks the environment and
//! draws the demo.

mod act;
mod bench;
mod exploration;
mod prometheus_metrics;
mod stream;

use anyhow::{Context, bail};
use burn::tensor::Device;
use clap::builder::TypedValueParser as _;
use clap::{Parser, Subcommand};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;
use tweezer_actor::config::ActorFile;
use tweezer_gym::{Baseline, EnvConfig, EvalSummary, Policy, Seeds, evaluate};
use tweezer_nets::{NetworkPolicy, PolicyFileError, SnapshotError};
use tweezer_process::init_logging;

/// Tweezer RL actor: steps virtual optical-tweezers environments.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    /// TOML config file: `[env]` and `[actor]` tables over the defaults of
    /// `docs/spec.md`.
    #[arg(long, global = true, value_name = "FILE")]
    config: Option<PathBuf>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Stream steps to the learner until SIGINT or SIGTERM (or --steps),
    /// then print a JSON report.
    Run {
        /// The learner's address (`host:port`) instead of `actor.learner`.
        #[arg(long, value_name = "ADDR")]
        learner: Option<String>,
        /// The security file: the CA that signed the learner's certificate
        /// and this actor's token (see docs/operations.md, Security).
        #[arg(long, env = tweezer_rpc::SECURITY_ENV, value_name = "FILE")]
        security: Option<PathBuf>,
        /// This actor's id instead of `actor.id`.
        #[arg(long)]
        id: Option<String>,
        /// Seed of the episodes and the noise instead of `actor.seed`.
        #[arg(long)]
        seed: Option<u64>,
        /// Stop once the learner has acknowledged this many steps.
        #[arg(long)]
        steps: Option<u64>,
        /// Serve Prometheus metrics here instead of `actor.metrics_listen`
        /// (the security file then needs cert, key and tokens).
        #[arg(long, value_name = "ADDR")]
        metrics_listen: Option<std::net::SocketAddr>,
        /// Log as JSON lines instead of text.
        #[arg(long)]
        log_json: bool,
    },
    /// Evaluate a policy over a list of episode seeds.
    Eval {
        /// `greedy` (straight at the target), `random` (uniform actions),
        /// `planner` (a receding-horizon search on the same observation), or
        /// the path of a policy snapshot (`.safetensors`).
        #[arg(long, default_value = "greedy")]
        policy: String,
        /// Episode seeds: `0..1000`, `5..=9`, `1,2,3`.
        #[arg(long, default_value = "0..1000")]
        seeds: Seeds,
        /// Episodes run side by side (the policy's batch).
        #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u64).range(1..).map(|b| b as usize))]
        batch: usize,
        /// Print one JSON object instead of a table.
        #[arg(long)]
        json: bool,
        /// Let a snapshot's actor act alone, without the learner's critics
        /// checking its actions (how TD3 explores, and how the Python
        /// package acts).
        #[arg(long)]
        actor_alone: bool,
    },
    /// Print a snapshot's actions for observations given as JSON lines
    /// (`{"centres": [[x, y], ...], "vector": [x, y]}`), one
    /// `{"action": [x, y]}` line each: the reference other implementations
    /// of a policy are checked against.
    Act {
        /// The policy snapshot (`.safetensors`).
        #[arg(long)]
        policy: PathBuf,
        /// The observations file (default: standard input).
        #[arg(long)]
        observations: Option<PathBuf>,
        /// Observations acted on at once (the policy's batch).
        #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u64).range(1..).map(|b| b as usize))]
        batch: usize,
        /// Let a snapshot's actor act alone, without the learner's critics
        /// checking its actions (how TD3 explores, and how the Python
        /// package acts).
        #[arg(long)]
        actor_alone: bool,
    },
    /// Measure environment and renderer speed.
    Bench {
        /// Seconds per repetition of each rate.
        #[arg(long, default_value_t = 1.0)]
        seconds: f64,
        /// Repetitions; rates are their median.
        #[arg(long, default_value_t = 5)]
        repetitions: usize,
        /// Print one JSON object instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Print the effective configuration (the file over the defaults of
    /// `docs/spec.md`) as TOML.
    Config,
    /// Run a policy (the greedy baseline unless told) on a few seeds and
    /// draw the paper's Figs. 5 and 6.
    Demo {
        /// `greedy`, `random`, `planner`, or the path of a policy snapshot.
        #[arg(long, default_value = "greedy")]
        policy: String,
        /// Episode seeds.
        #[arg(long, default_value = "0..4")]
        seeds: Seeds,
        /// Directory the pictures go to.
        #[arg(long, default_value = "demo-out")]
        out: PathBuf,
    },
}

/// The policy in snapshot file `path`. A snapshot of another environment
/// (a CNN of another resolution) is refused naming the config that fits
/// it: the `actor.toml` of the run whose `snapshots/` hold it. With
/// `actor_alone`, the learner's critics do not check the actor.
fn snapshot_policy(
    path: &Path,
    env: &EnvConfig,
    actor_alone: bool,
) -> anyhow::Result<NetworkPolicy> {
    match NetworkPolicy::from_file(path, env, &Device::flex()) {
        Ok((policy, _)) if actor_alone => Ok(policy.actor_alone()),
        Ok((policy, _)) => Ok(policy),
        Err(
            e @ PolicyFileError::Snapshot {
                source: SnapshotError::Mismatch { .. },
                ..
            },
        ) => {
            // A run directory holds `snapshots/` and the actors' `actor.toml`.
            let run = path
                .parent()
                .filter(|dir| dir.file_name().is_some_and(|n| n == "snapshots"))
                .and_then(Path::parent)
                .map_or_else(
                    || "RUN".into(),
                    |run| match run.as_os_str().is_empty() {
                        true => ".".into(),
                        false => run.display().to_string(),
                    },
                );
            let hint = format!(
                "evaluate it with the config of the run that trained it: --config {run}/actor.toml"
            );
            bail!("{e}; {hint}")
        }
        Err(e) => Err(e.into()),
    }
}

/// A baseline's name, or the path of a snapshot file (see
/// [`snapshot_policy`] for `actor_alone`).
fn policy_named(name: &str, env: &EnvConfig, actor_alone: bool) -> anyhow::Result<Box<dyn Policy>> {
    if let Some(baseline) = Baseline::named(name) {
        return Ok(baseline.policy(env));
    }
    let path = Path::new(name);
    if path.is_file() {
        return Ok(Box::new(snapshot_policy(path, env, actor_alone)?));
    }
    if path.is_dir() {
        bail!(
            "policy {name} is a directory: name a snapshot file in it (a run's snapshots are in RUN/snapshots/)"
        );
    }
    // A name with a path separator or an extension was meant as a file.
    if name.contains(std::path::MAIN_SEPARATOR) || path.extension().is_some() {
        bail!("policy file {name} does not exist");
    }
    bail!(
        "unknown policy `{name}`: use {}, or the path of a snapshot file",
        Baseline::names()
    )
}

/// A policy whose acting is timed: the time a step's decision takes, the
/// figure that must fit the instrument's control period.
struct Timed {
    policy: Box<dyn Policy>,
    elapsed: Duration,
    observations: usize,
}

impl Timed {
    fn new(policy: Box<dyn Policy>) -> Self {
        Self {
            policy,
            elapsed: Duration::ZERO,
            observations: 0,
        }
    }

    /// Mean wall time per observation acted on, µs.
    fn per_observation_us(&self) -> f64 {
        self.elapsed.as_secs_f64() * 1e6 / self.observations.max(1) as f64
    }
}

impl Policy for Timed {
    fn act(
        &mut self,
        observations: &[&tweezer_gym::Observation],
        actions: &mut [tweezer_gym::Action],
    ) {
        let started = std::time::Instant::now();
        self.policy.act(observations, actions);
        self.elapsed += started.elapsed();
        self.observations += observations.len();
    }
}

fn print_summary(summary: &EvalSummary, json: bool) -> anyhow::Result<()> {
    if json {
        println!("{}", serde_json::to_string(summary)?);
    } else {
        println!("episodes        {}", summary.episodes);
        println!("success rate    {:.3}", summary.success_rate);
        println!("collision rate  {:.3}", summary.collision_rate);
        println!("timeout rate    {:.3}", summary.timeout_rate);
        println!("mean return     {:.1}", summary.mean_return);
        println!("mean steps      {:.1}", summary.mean_steps);
        if let Some(steps) = summary.mean_steps_success {
            println!("  of successes  {steps:.1}");
        }
    }
    Ok(())
}

fn main() -> std::process::ExitCode {
    tweezer_process::exit_status(run())
}

fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let mut config = ActorFile::load(cli.config.as_deref())?;
    match cli.command {
        Command::Run {
            learner,
            id,
            seed,
            steps,
            metrics_listen,
            log_json,
            security,
        } => {
            if metrics_listen.is_some() {
                config.actor.metrics_listen = metrics_listen;
            }
            // Its metrics listener reloads tokens on SIGHUP.
            if config.actor.metrics_listen.is_some() {
                tweezer_process::catch_early_hangups();
            }
            init_logging(log_json);
            let security = tweezer_rpc::Security::load(security.as_deref())?;
            let metrics = config
                .actor
                .metrics_listen
                .map(|_| tweezer_rpc::ServerSecurity::load(&security))
                .transpose()?;
            let security = tweezer_rpc::ClientSecurity::load(&security)?;
            if let Some(url) = learner {
                config.actor.learner = url;
            }
            if let Some(id) = id {
                config.actor.id = id;
            }
            if let Some(seed) = seed {
                config.actor.seed = seed;
            }
            config.actor.validate().map_err(|e| e.in_table("actor"))?;
            if steps == Some(0) {
                bail!("--steps must be at least 1");
            }
            let report = stream::run(
                config,
                security,
                metrics,
                steps,
                Arc::new(AtomicBool::new(false)),
            )?;
            println!("{}", serde_json::to_string(&report)?);
        }
        Command::Eval {
            policy,
            seeds,
            batch,
            json,
            actor_alone,
        } => {
            let mut policy = Timed::new(policy_named(&policy, &config.env, actor_alone)?);
            let episodes = evaluate(&config.env, &mut policy, &seeds.0, batch)?;
            let summary = EvalSummary::of(&episodes);
            let per_observation_us = policy.per_observation_us();
            if json {
                #[derive(serde::Serialize)]
                struct Eval {
                    #[serde(flatten)]
                    summary: EvalSummary,
                    policy_us_per_observation: f64,
                }
                let eval = Eval {
                    summary,
                    policy_us_per_observation: per_observation_us,
                };
                println!("{}", serde_json::to_string(&eval)?);
            } else {
                print_summary(&summary, false)?;
                println!(
                    "policy time     {per_observation_us:.1} µs per observation (batches of up to {batch})"
                );
            }
        }
        Command::Act {
            policy,
            observations,
            batch,
            actor_alone,
        } => {
            let mut policy = snapshot_policy(&policy, &config.env, actor_alone)?;
            let stdout = std::io::stdout().lock();
            match observations {
                Some(path) => {
                    let file = std::fs::File::open(&path)
                        .with_context(|| format!("cannot open {}", path.display()))?;
                    act::run(
                        &config.env,
                        &mut policy,
                        std::io::BufReader::new(file),
                        stdout,
                        batch,
                    )?
                }
                None => act::run(
                    &config.env,
                    &mut policy,
                    std::io::stdin().lock(),
                    stdout,
                    batch,
                )?,
            };
        }
        Command::Bench {
            seconds,
            repetitions,
            json,
        } => {
            if !(seconds.is_finite() && seconds > 0.0) {
                bail!("--seconds must be a positive number, got {seconds}");
            }
            let report = bench::run(&config.env, Duration::from_secs_f64(seconds), repetitions)?;
            if json {
                println!("{}", serde_json::to_string(&report)?);
            } else {
                println!(
                    "env steps/s, 1 core      {:.0}",
                    report.env_steps_per_sec_1core
                );
                println!(
                    "env steps/s, {} threads   {:.0} ({} envs)",
                    report.threads, report.env_steps_per_sec_all_cores, report.vec_envs
                );
                println!("render, full (median)    {:.2} µs", report.render_us_median);
                println!(
                    "render, incremental      {:.2} µs",
                    report.render_incremental_us_median
                );
                println!(
                    "resolution {}x{}, median of {} repetitions",
                    report.resolution[0], report.resolution[1], report.repetitions
                );
                for a in &report.acting {
                    println!(
                        "acting, {:<5} net, {:>2} envs  {:>8.0} steps/s ({:.0} % inference; infer b1 {:.3} ms, b16 {:.3} ms)",
                        a.network,
                        a.envs,
                        a.actor_steps_per_sec,
                        100.0 * a.inference_share,
                        a.actor_infer_ms_batch1,
                        a.actor_infer_ms_batch16
                    );
                }
                let mut seen = std::collections::BTreeSet::new();
                for a in report.acting.iter().filter(|a| seen.insert(a.network)) {
                    println!("  {}: {}", a.network, a.architecture);
                }
            }
        }
        Command::Config => print!("{}", config.to_toml()),
        Command::Demo { policy, seeds, out } => {
            let mut policy = policy_named(&policy, &config.env, false)?;
            let pictures =
                tweezer_figures::draw_episodes(&config.env, policy.as_mut(), &seeds.0, &out)?;
            for path in &pictures.written {
                println!("wrote {}", path.display());
            }
            print_summary(&pictures.summary, false)?;
        }
    }
    Ok(())
}
