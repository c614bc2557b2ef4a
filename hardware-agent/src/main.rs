//! The hardware-agent command line: `run` (episodes on the instrument or
//! its digital twin), `home` (the stages, once after power-up), `cameras`
//! (the GenICam cameras found), `segment`
//! (sphere centres in image files, for tuning segmentation on an
//! instrument's own frames), `bench` and `config`.

mod commands;
mod daemon;

use clap::{Parser, Subcommand};
use std::path::PathBuf;
use tweezer_gym::Baseline;
use tweezer_hardware_agent::config::AgentConfig;

/// Tweezer RL hardware agent: drives the microscope's stages with a trained
/// policy, on the instrument or on its digital twin.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    /// TOML config file (`[env]`, `[segmentation]`, `[stages]`, `[control]`,
    /// `[policy]`, `[camera]`, `[overlay]`, `[service]`, `[records]`,
    /// `[twin]`); defaults otherwise.
    #[arg(long = "config", global = true, value_name = "FILE")]
    config: Option<PathBuf>,
    /// The security file: for `serve`, the certificate, key and accepted
    /// tokens; for a learner's snapshot, its CA and a read token (see
    /// docs/operations.md, Security).
    #[arg(long, global = true, env = tweezer_rpc::SECURITY_ENV, value_name = "FILE")]
    security: Option<PathBuf>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Print the effective configuration (the file over defaults) as TOML.
    Config,
    /// Home both stages (each runs to its home limit switch, which zeroes
    /// its counter) and park them in the middle of their soft limits; one
    /// JSON line. Needed once after the controllers power up: until then
    /// `run` and `serve` refuse to drive them (`stages.require_homed`).
    Home,
    /// Measure the calibration: move each stage a few small distances
    /// within its soft limits and follow the free spheres in the image;
    /// prints `px_per_um`, `image_x`, `x_sign`, `y_sign`, each stage's
    /// backlash and the residual, and with --write sets them in a config
    /// file's `[stages]`. Refused when the scene has too few free spheres
    /// or the moves disagree.
    Calibrate {
        /// Calibrate the digital twin (its `[twin.truth]`, if set, is what
        /// it should find).
        #[arg(long)]
        twin: bool,
        /// The twin's scene (the seed of its free spheres).
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Each move, µm: more than the backlash, small enough that the
        /// spheres stay in view.
        #[arg(long, default_value_t = 20.0)]
        move_um: f64,
        /// Set the calibration in this config file's `[stages]` table
        /// (created if missing; its other settings and comments kept).
        #[arg(long, value_name = "FILE")]
        write: Option<PathBuf>,
        /// One JSON object instead of text.
        #[arg(long)]
        json: bool,
    },
    /// List the GenICam cameras found (GigE Vision by broadcast, USB3
    /// Vision on the bus), or describe the one at ADDRESS: id, vendor and
    /// model, serial number, address and pixel formats. Needs a build with
    /// the `aravis` feature.
    Cameras {
        /// A camera's IP address, id or serial number (a camera on another
        /// subnet, or on loopback, is reached only by its address).
        address: Option<String>,
        /// One JSON object per camera.
        #[arg(long)]
        json: bool,
    },
    /// Run episodes, each recorded (JSON lines and a picture) under the
    /// records directory; prints one JSON line per episode.
    Run {
        /// Drive the digital twin (simulated KDC101s on pseudo-terminals
        /// and a rendered camera) instead of the instrument.
        #[arg(long)]
        twin: bool,
        /// Episodes to run.
        #[arg(long, default_value_t = 1)]
        episodes: u64,
        /// The twin's first episode seed (its spheres and target).
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Target relative to the trap, µm along the image axes (required
        /// on the instrument).
        #[arg(long, value_name = "DX,DY", value_parser = tweezer_process::parse_pair, allow_hyphen_values = true)]
        target_um: Option<[f64; 2]>,
        /// Drive with the greedy baseline instead of the configured policy.
        #[arg(long, conflicts_with_all = ["snapshot", "planner"])]
        greedy: bool,
        /// Drive with the planner baseline instead of the configured policy.
        #[arg(long, conflicts_with = "snapshot")]
        planner: bool,
        /// Drive with this snapshot file instead of the configured policy.
        #[arg(long, value_name = "FILE")]
        snapshot: Option<PathBuf>,
        #[command(flatten)]
        overrides: LoopOverrides,
    },
    /// Serve the gRPC control service (status, episodes, stops, policy,
    /// overlay, telemetry) until SIGINT or SIGTERM; prints
    /// `hardware-agent listening on ADDR` once ready.
    Serve {
        /// Drive the digital twin instead of the instrument.
        #[arg(long)]
        twin: bool,
        /// Start with the greedy baseline instead of the configured policy.
        #[arg(long, conflicts_with = "planner")]
        greedy: bool,
        /// Start with the planner baseline instead of the configured policy.
        #[arg(long)]
        planner: bool,
        /// Address to listen on (overrides `service.listen`).
        #[arg(long, value_name = "ADDR")]
        listen: Option<std::net::SocketAddr>,
        /// Serve Prometheus metrics here (overrides
        /// `service.metrics_listen`).
        #[arg(long, value_name = "ADDR")]
        metrics_listen: Option<std::net::SocketAddr>,
        #[command(flatten)]
        overrides: LoopOverrides,
        /// Log JSON lines instead of text.
        #[arg(long)]
        log_json: bool,
    },
    /// Find the spheres in PNG or TIFF frames (8 or 16 bits) with the
    /// configured segmentation. Centres are in pixels with pixel (i, j)
    /// spanning [i, i+1) × [j, j+1), so its centre is (i + 0.5, j + 0.5);
    /// subtract 0.5 for the convention of OpenCV, scikit-image and trackpy.
    Segment {
        /// Frame files.
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// One JSON line per file: {"file": ..., "centres": [[x, y], ...]}.
        #[arg(long)]
        json: bool,
    },
    /// Measure segmentation speed and detection quality on twin frames,
    /// then the control loop on the twin against the virtual environment.
    Bench {
        /// Frames per focus and noise setting.
        #[arg(long, default_value_t = 12)]
        frames: u64,
        /// Episodes per policy on the twin and in the virtual environment
        /// (0: segmentation only).
        #[arg(long, default_value_t = 20)]
        episodes: u64,
        /// The first episode seed.
        #[arg(long, default_value_t = 100_000)]
        seed: u64,
        /// A trained snapshot to measure besides the greedy and planner
        /// baselines.
        #[arg(long, value_name = "FILE")]
        snapshot: Option<PathBuf>,
        /// Control rate on the twin, Hz (overrides `control.rate_hz`: the
        /// twin keeps up with faster rates than the stages' 4 Hz; much
        /// faster, and their finite acceleration no longer takes up the
        /// backlash within a step).
        #[arg(long, default_value_t = 10.0)]
        rate: f64,
        /// Instead, measure the configured GenICam camera
        /// (`[camera.genicam]`): frame-to-command latency in free-run and
        /// with a software trigger, this many steps each, commanding the
        /// twin's simulated stages.
        #[arg(long, value_name = "STEPS")]
        camera: Option<usize>,
        /// One JSON object instead of a table.
        #[arg(long)]
        json: bool,
    },
}

/// The baseline `--greedy` or `--planner` asks for (clap lets at most one
/// through).
fn baseline_flag(greedy: bool, planner: bool) -> Option<Baseline> {
    match (greedy, planner) {
        (true, _) => Some(Baseline::Greedy),
        (_, true) => Some(Baseline::Planner),
        _ => None,
    }
}

fn main() -> std::process::ExitCode {
    tweezer_process::exit_status(run())
}

fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    if matches!(cli.command, Command::Serve { .. }) {
        tweezer_process::catch_early_hangups();
    }
    let mut config = AgentConfig::load(cli.config.as_deref())?;
    match cli.command {
        Command::Config => print!("{}", config.to_toml()),
        Command::Home => commands::home::run(&config)?,
        Command::Calibrate {
            twin,
            seed,
            move_um,
            write,
            json,
        } => commands::calibrate::run(
            &config,
            &commands::calibrate::CalibrateArgs {
                twin,
                seed,
                move_um,
                write,
                json,
            },
        )?,
        Command::Cameras { address, json } => commands::cameras::run(address.as_deref(), json)?,
        Command::Run {
            twin,
            episodes,
            seed,
            target_um,
            greedy,
            planner,
            snapshot,
            overrides,
        } => {
            overrides.apply(&mut config)?;
            let args = commands::run::RunArgs {
                twin,
                episodes,
                seed,
                target_um,
                baseline: baseline_flag(greedy, planner),
                snapshot,
            };
            let security = match tweezer_rpc::Security::load(cli.security.as_deref()) {
                Ok(security) => Some(security),
                Err(tweezer_rpc::SecurityError::Missing) => None,
                Err(e) => return Err(e.into()),
            };
            commands::run::run(&config, args, security.as_ref())?;
        }
        Command::Serve {
            twin,
            greedy,
            planner,
            listen,
            metrics_listen,
            overrides,
            log_json,
        } => {
            if let Some(listen) = listen {
                config.service.listen = listen;
            }
            if metrics_listen.is_some() {
                config.service.metrics_listen = metrics_listen;
            }
            overrides.apply(&mut config)?;
            let security = tweezer_rpc::Security::load(cli.security.as_deref())?;
            daemon::serve(
                config,
                security,
                twin,
                baseline_flag(greedy, planner),
                log_json,
            )?;
        }
        Command::Segment { files, json } => commands::segment::run(&config, &files, json)?,
        Command::Bench {
            frames,
            episodes,
            seed,
            snapshot,
            rate,
            camera,
            json,
        } => {
            config.control.rate_hz = rate;
            config.validate()?;
            if let Some(steps) = camera {
                return commands::bench::camera(&config, steps, json);
            }
            let args = commands::bench::BenchArgs {
                frames,
                episodes,
                seed,
                snapshot,
                json,
            };
            commands::bench::run(&config, &args)?;
        }
    }
    Ok(())
}

/// Settings of the loop a command may override.
#[derive(clap::Args)]
struct LoopOverrides {
    /// Control rate, Hz (overrides `control.rate_hz`).
    #[arg(long)]
    rate: Option<f64>,
    /// Where records go (overrides `records.dir`).
    #[arg(long, value_name = "DIR")]
    records: Option<PathBuf>,
}

impl LoopOverrides {
    /// Writes the overrides into `config` and checks it again.
    fn apply(self, config: &mut AgentConfig) -> anyhow::Result<()> {
        if let Some(rate) = self.rate {
            config.control.rate_hz = rate;
        }
        if let Some(records) = self.records {
            config.records.dir = records;
        }
        Ok(config.validate()?)
    }
}
