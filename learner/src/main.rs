//! The learner process. It will hold the FIFO replay, train TD3 and serve
//! policy snapshots over gRPC (the learner issue); today it reads and checks
//! the configuration the whole run shares.

use clap::{Parser, Subcommand};
use tweezer_gym::ConfigArgs;

/// Tweezer RL learner. Replay, TD3 training and the gRPC service are not
/// built yet; `config` checks a config file and prints what it means.
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
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let config = cli.config.load()?;
    match cli.command {
        Command::Config => print!("{}", config.to_toml()),
    }
    Ok(())
}
