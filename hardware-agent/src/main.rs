//! The hardware-agent daemon's command line. Today: `segment` (sphere
//! centres in image files, for tuning segmentation on an instrument's own
//! frames), `bench` and `config`.

mod bench;
mod segment_files;

use clap::{Parser, Subcommand};
use std::path::PathBuf;
use tweezer_hardware_agent::config::AgentConfig;

/// Tweezer RL hardware agent: drives the microscope's stages with a trained
/// policy (the control loop, the twin's stages and the gRPC service are not
/// built yet).
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    /// TOML config file (`[env]`, `[segmentation]`, `[twin]`); defaults
    /// otherwise.
    #[arg(long = "config", global = true, value_name = "FILE")]
    config: Option<PathBuf>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Print the effective configuration (the file over defaults) as TOML.
    Config,
    /// Find the spheres in PNG or TIFF frames (8 or 16 bits) with the
    /// configured segmentation.
    Segment {
        /// Frame files.
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// One JSON line per file: {"file": ..., "centres": [[x, y], ...]}.
        #[arg(long)]
        json: bool,
    },
    /// Measure segmentation speed and detection quality on twin frames.
    Bench {
        /// Frames per focus and noise setting.
        #[arg(long, default_value_t = 12)]
        frames: u64,
        /// One JSON object instead of a table.
        #[arg(long)]
        json: bool,
    },
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let config = AgentConfig::load(cli.config.as_deref())?;
    match cli.command {
        Command::Config => print!("{}", config.to_toml()),
        Command::Segment { files, json } => segment_files::run(&config, &files, json)?,
        Command::Bench { frames, json } => bench::run(&config, frames, json)?,
    }
    Ok(())
}
