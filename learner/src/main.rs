//! The learner process: `serve` trains behind the gRPC service, `config`
//! prints the effective configuration, `bench` measures the parts.

use anyhow::bail;
use clap::{Parser, Subcommand};
use std::net::SocketAddr;
use std::path::PathBuf;
use tweezer_learner::config::LearnerFile;
use tweezer_learner::serve::{Start, serve};
use tweezer_process::init_logging;

/// Tweezer RL learner: FIFO replay, TD3 in Burn, versioned policy snapshots
/// over gRPC.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    /// TOML config file: `[env]` and `[learner]` tables over the defaults of
    /// `docs/spec.md`.
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
        /// The security file: certificate, key, accepted tokens (see
        /// docs/operations.md, Security).
        #[arg(long, env = tweezer_rpc::SECURITY_ENV, value_name = "FILE")]
        security: Option<PathBuf>,
    },
    /// Check the configuration, `learner.device` included (this build
    /// must be able to open it), and print it in effect (the file over the
    /// defaults of `docs/spec.md`) as TOML.
    Config,
    /// Measure TD3 updates (with `learner.td3`), inference and replay memory
    /// on `learner.device`.
    Bench {
        /// TD3 updates timed (rounded up to an even number).
        #[arg(long, default_value_t = 4)]
        updates: usize,
        /// Transitions per update instead of `learner.batch_size`.
        #[arg(long)]
        batch_size: Option<usize>,
        /// Replay capacity filled to measure bytes per transition.
        #[arg(long, default_value_t = 1_050_000)]
        replay_capacity: usize,
        /// Print one JSON object instead of a table.
        #[arg(long)]
        json: bool,
    },
}

/// mimalloc keeps freed pages for reuse: a TD3 update allocates and frees
/// hundreds of megabytes of tensors, and glibc's malloc gives them back to
/// the kernel, which must fault them in and zero them again next update.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// How long mimalloc keeps freed memory before it returns it to the
/// system, ms. Its default, 1 s, can be shorter than one update of a large
/// network on a CPU, and then each update's tensors (activations, the
/// target passes' outputs: hundreds of megabytes) would be faulted in and
/// zeroed by the kernel afresh. An idle learner still gives memory back.
const PURGE_DELAY_MS: &str = "30000";

/// mimalloc reads its options from the environment before `main`: a
/// learner started without `MIMALLOC_PURGE_DELAY` replaces itself once
/// (same process, same arguments) with [`PURGE_DELAY_MS`] set. Returns
/// only if that is not needed or fails, saying why.
fn with_allocator_options() -> Option<String> {
    use std::os::unix::process::CommandExt;
    const OPTION: &str = "MIMALLOC_PURGE_DELAY";
    if std::env::var_os(OPTION).is_some() {
        return None;
    }
    let mut args = std::env::args_os();
    let exe = match std::env::current_exe() {
        Ok(exe) => exe,
        Err(e) => return Some(format!("cannot find the learner's executable: {e}")),
    };
    let mut command = std::process::Command::new(exe);
    if let Some(arg0) = args.next() {
        command.arg0(arg0);
    }
    // A SIGHUP sent while the process replaces itself waits for `run`.
    tweezer_process::hold_hangups();
    let error = command.args(args).env(OPTION, PURGE_DELAY_MS).exec();
    tweezer_process::release_hangups();
    Some(format!("cannot re-execute with {OPTION} set: {error}"))
}

fn main() -> std::process::ExitCode {
    tweezer_process::exit_status(run())
}

fn run() -> anyhow::Result<()> {
    let unset = with_allocator_options();
    let cli = Cli::parse();
    if matches!(cli.command, Command::Serve { .. }) {
        tweezer_process::catch_early_hangups();
    } else {
        tweezer_process::release_hangups();
    }
    init_logging(cli.log_json);
    if let Some(why) = unset {
        tracing::warn!("{why}; freed memory goes back to the system after mimalloc's 1 s");
    }
    match cli.command {
        Command::Serve {
            resume,
            listen,
            metrics_listen,
            run_dir,
            auto_resume,
            security,
        } => {
            let mut file = match (&cli.config, &resume) {
                (None, Some(dir)) => LearnerFile::of_run(dir)?,
                (path, _) => LearnerFile::load(path.as_deref())?,
            };
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
        Command::Config => {
            let file = LearnerFile::load(cli.config.as_deref())?;
            file.learner.device.device()?;
            print!("{}", file.to_toml());
        }
        Command::Bench {
            updates,
            batch_size,
            replay_capacity,
            json,
        } => {
            if replay_capacity == 0 {
                bail!("--replay-capacity must be at least 1");
            }
            let mut config = LearnerFile::load(cli.config.as_deref())?;
            if let Some(batch_size) = batch_size {
                config.learner.batch_size = batch_size;
            }
            let report = tweezer_learner::bench::run(
                &config.env,
                &config.learner,
                replay_capacity,
                updates,
            )?;
            if json {
                println!("{}", serde_json::to_string(&report)?);
            } else {
                println!("networks                 {}", report.architecture);
                println!("device                   {}", report.device);
                println!(
                    "TD3 update, batch {:<6}  {:.2} ms",
                    report.batch_size, report.update_ms_mean
                );
                println!("  critic step            {:.2} ms", report.critic_step_ms);
                println!("  actor step             {:.2} ms", report.actor_step_ms);
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
