//! `tweezer`, the operator's command line: the status of the learner and
//! the hardware agent as a table or JSON, once or watched; snapshot
//! downloads; control of the learner (pause, resume, checkpoint) and of the
//! hardware agent (episodes, stops, the emergency stop, policies, virtual
//! obstacles, telemetry); and the deployment's certificates and tokens.

mod agent;
mod connect;
mod credentials;
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
    /// The security file: the CA that signed the services' certificates,
    /// this client's token file (`TWEEZER_TOKEN` overrides it) and, for
    /// services that require one, its certificate.
    #[arg(long, global = true, env = tweezer_rpc::SECURITY_ENV, value_name = "FILE")]
    security: Option<PathBuf>,
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
    /// Check a service's health (`grpc.health.v1`, no token needed):
    /// prints its status and exits 0 only when it is SERVING. For
    /// Kubernetes exec probes and scripts.
    Health {
        /// The service's gRPC address.
        #[arg(long)]
        address: String,
        /// The service to ask about (`tweezer.v1.Learner`,
        /// `tweezer.v1.HardwareAgent`); the whole server by default.
        #[arg(long, default_value = "")]
        service: String,
    },
    /// Certificates: the deployment's CA, and one for each process.
    Cert {
        #[command(subcommand)]
        command: CertCommand,
    },
    /// Bearer tokens.
    Token {
        #[command(subcommand)]
        command: TokenCommand,
    },
}

/// Certificate commands.
#[derive(Subcommand)]
pub enum CertCommand {
    /// Make the deployment's CA: OUT/ca.crt and OUT/ca.key.
    Ca {
        /// The directory to write to.
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
        /// The CA's common name.
        #[arg(long, default_value = "tweezer-rl CA")]
        name: String,
        /// Days it is valid.
        #[arg(long, default_value_t = 3650)]
        days: u32,
    },
    /// Issue a certificate for a process (served, and presented as a client
    /// certificate): OUT/NAME.crt and OUT/NAME.key.
    Issue {
        /// The directory holding ca.crt and ca.key.
        #[arg(long, value_name = "DIR")]
        ca: PathBuf,
        /// The certificate's name (`learner`, `agent`, `actor-3`, ...).
        #[arg(long)]
        name: String,
        /// A DNS name or IP address clients reach it by (repeatable).
        #[arg(long = "host", value_name = "HOST")]
        hosts: Vec<String>,
        /// The directory to write to.
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
        /// Days it is valid.
        #[arg(long, default_value_t = 365)]
        days: u32,
        /// The security file of the process it is for: `ca`, `cert` and
        /// `key` are set in it (created if absent; the rest is kept).
        #[arg(long, value_name = "FILE")]
        write_security: Option<PathBuf>,
    },
}

/// Token commands.
#[derive(Subcommand)]
pub enum TokenCommand {
    /// Make a token: the secret goes to --out (mode 0600), its SHA-256 is
    /// appended to the services' tokens file.
    New {
        /// `read` (status, snapshots, telemetry), `actor` (stream
        /// transitions, and read) or `control` (everything that changes
        /// state or moves the stages, and read).
        #[arg(long)]
        role: String,
        /// Whose it is: logged with each state-changing call it makes.
        #[arg(long)]
        name: String,
        /// The tokens file the services read (created if absent).
        #[arg(long, value_name = "FILE")]
        tokens: PathBuf,
        /// Where the token goes (must not exist).
        #[arg(long, value_name = "FILE")]
        out: PathBuf,
        /// The security file of the client that sends it: `token_file` is
        /// set in it (created if absent; the rest is kept).
        #[arg(long, value_name = "FILE")]
        write_security: Option<PathBuf>,
        /// With --write-security: the directory holding the CA's ca.crt,
        /// set as the client's `ca` (what it checks services against).
        #[arg(long, value_name = "DIR", requires = "write_security")]
        ca: Option<PathBuf>,
        /// The security file of a service that accepts it: `tokens` is set
        /// in it (repeatable).
        #[arg(long = "accepted-by", value_name = "FILE")]
        accepted_by: Vec<PathBuf>,
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
    /// The actors the learner has heard from: streams open, steps and
    /// episodes since it started, time since their last batch.
    Actors,
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
        #[arg(long, value_name = "DX,DY", value_parser = tweezer_process::parse_pair, allow_hyphen_values = true, conflicts_with = "absolute_mm")]
        target_um: Option<[f64; 2]>,
        /// Target as stage positions X,Y, mm.
        #[arg(long, value_name = "X,Y", value_parser = tweezer_process::parse_pair)]
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
        /// The planner baseline (dodges without training).
        #[arg(long, group = "source")]
        planner: bool,
        /// Follow the learner's "best" or "latest": load it now, and each
        /// newer snapshot it publishes under that tag between episodes.
        #[arg(long, group = "source", value_name = "TAG")]
        follow: Option<String>,
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

fn main() -> std::process::ExitCode {
    tweezer_process::exit_status(run())
}

fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let security = cli.security.as_deref();
    runtime.block_on(async {
        match cli.command {
            Group::Learner { learner, command } => {
                learner::run(security, &learner, command, cli.json).await
            }
            Group::Agent { agent, command } => {
                agent::run(security, &agent, command, cli.json).await
            }
            Group::Health { address, service } => {
                connect::health(security, &address, &service).await
            }
            Group::Cert { command } => credentials::cert(command),
            Group::Token { command } => credentials::token(command),
        }
    })
}
