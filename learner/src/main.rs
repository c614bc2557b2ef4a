//! The learner process. Today: the configuration check and the benchmark of
//! the replay, the TD3 update and gRPC ingest; `serve` comes with the rest
//! of the learner issue.

use anyhow::bail;
use burn::tensor::Device;
use clap::{Parser, Subcommand};
use tweezer_gym::ConfigArgs;

/// Tweezer RL learner. Replay, TD3, the rate limiter and the ingest service
/// are built and benchmarked; `serve` (training behind the service) is not
/// built yet.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    #[command(flatten)]
    config: ConfigArgs,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
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

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let config = cli.config.load()?;
    match cli.command {
        Command::Config => print!("{}", config.to_toml()),
        Command::Bench {
            updates,
            replay_capacity,
            json,
        } => {
            if replay_capacity == 0 {
                bail!("--replay-capacity must be at least 1");
            }
            let report = tweezer_learner::bench::run(
                &config.env,
                replay_capacity,
                updates,
                &Device::flex(),
            )?;
            if json {
                println!("{}", serde_json::to_string(&report)?);
            } else {
                println!("TD3 update, batch 32     {:.0} ms", report.update_ms_mean);
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
                    "gRPC ingest, 8 streams   {:.0} transitions/s",
                    report.ingest_transitions_per_sec
                );
            }
        }
    }
    Ok(())
}
