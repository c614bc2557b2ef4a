//! `tweezer`, the operator's command line: the status of the learner and
//! the hardware agent as a table or JSON, once or watched; snapshot
//! downloads; and control of the hardware agent (episodes, stops, the
//! emergency stop, policies, virtual obstacles, telemetry).

mod agent;
mod connect;
mod fields;
mod learner;
mod watch;

use clap::{Parser, Subcommand};
use std::path::PathBuf;

/// Tweezer RL operator CLI.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    /// Print JSON (one object per line) instead of tables.
    #[arg(long, global = true)]
    json: bool,
    #[command(subcommand)]
    command: Group,
}

#[derive(Subcommand)]
enum Group {
    /// The learner.
    Learner {
        /// The learner's gRPC address.
        #[arg(long, env = "TWEEZER_LEARNER", default_value = "127.0.0.1:50051")]
        learner: String,
        #[command(subcommand)]
        command: LearnerCommand,
    },
    /// The hardware agent.
    Agent {
        /// The hardware agent's gRPC address.
        #[arg(long, env = "TWEEZER_AGENT", default_value = "127.0.0.1:50061")]
        agent: String,
        #[command(subcommand)]
        command: AgentCommand,
    },
}

/// What to ask the learner.
#[derive(Subcommand)]
pub enum LearnerCommand {
    /// Steps, updates, buffer, rates, limiter, actors, returns, snapshots,
    /// losses.
    Status {
        /// Refresh every SECS seconds until interrupted.
        #[arg(long, value_name = "SECS")]
        watch: Option<f64>,
    },
    /// The snapshots the learner keeps, with their metadata and checksums.
    Snapshots,
    /// Stop updating the networks (actors are held back meanwhile).
    Pause,
    /// Update the networks again.
    Resume,
    /// Write a checkpoint now and print its path.
    Checkpoint,
    /// Download a policy snapshot (checked against its size and SHA-256).
    Download {
        /// "best", "latest" or a version number.
        snapshot: String,
        /// Where to write it.
        #[arg(long, short)]
        out: PathBuf,
    },
}

/// What to ask the hardware agent.
#[derive(Subcommand)]
pub enum AgentCommand {
    /// State, episode, stage positions, loop timing, policy.
    Status {
        /// Refresh every SECS seconds until interrupted.
        #[arg(long, value_name = "SECS")]
        watch: Option<f64>,
    },
    /// Start an episode toward a target.
    Start {
        /// Target relative to the trap, µm along the image axes.
        #[arg(long, value_name = "DX,DY", value_parser = tweezer_gym::parse_pair, allow_hyphen_values = true, conflicts_with = "absolute_mm")]
        target_um: Option<[f64; 2]>,
        /// Target as stage positions X,Y, mm.
        #[arg(long, value_name = "X,Y", value_parser = tweezer_gym::parse_pair)]
        absolute_mm: Option<[f64; 2]>,
        /// Digital twin only: lay out this episode seed (and, without a
        /// target, aim at its target).
        #[arg(long)]
        twin_seed: Option<u64>,
        /// Wait for the episode to end and print how it did.
        #[arg(long)]
        wait: bool,
    },
    /// Stop the running episode (profiled stop).
    Stop,
    /// Emergency stop: both stages stop at once; motion is refused until
    /// `reset`.
    Estop {
        /// Why, for the log.
        #[arg(long, default_value = "operator emergency stop")]
        reason: String,
    },
    /// Clear an emergency stop or a fault.
    Reset,
    /// Replace the policy.
    Load {
        /// A snapshot file on the agent's machine.
        #[arg(long, group = "source")]
        file: Option<String>,
        /// A snapshot of the agent's learner: "best", "latest" or a version.
        #[arg(long, group = "source")]
        learner: Option<String>,
        /// The greedy baseline.
        #[arg(long, group = "source")]
        greedy: bool,
    },
    /// Replace the virtual obstacles with those of an overlay file (TOML:
    /// `discs_um`, `[[walls]]`); an empty file clears them.
    Overlay {
        /// The overlay file.
        file: PathBuf,
    },
    /// Print telemetry as episodes run.
    Telemetry {
        /// Stop after this many messages.
        #[arg(long)]
        count: Option<u64>,
    },
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        match cli.command {
            Group::Learner { learner, command } => learner::run(&learner, command, cli.json).await,
            Group::Agent { agent, command } => agent::run(&agent, command, cli.json).await,
        }
    })
}
