//! `hardware-agent run`: episodes on the instrument (or with `--twin` on the
//! digital twin), each recorded with its picture; one JSON line each.

use anyhow::{Context, bail};
use serde_json::json;
use std::path::PathBuf;
use tweezer_gym::Baseline;
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_hardware_agent::control::{Halt, HaltKind};
use tweezer_hardware_agent::instrument::Instrument;
use tweezer_hardware_agent::policy_source::{LoadedPolicy, PolicyChoice};
use tweezer_hardware_agent::record::EpisodeHeader;
use tweezer_process::{StopSignals, init_logging};
use tweezer_rpc::Security;

/// What `run` was asked for.
pub struct RunArgs {
    /// Drive the digital twin instead of the instrument.
    pub twin: bool,
    /// Episodes to run.
    pub episodes: u64,
    /// The twin's first episode seed.
    pub seed: u64,
    /// Target relative to the trap, µm (image axes); the twin draws one
    /// from the seed otherwise.
    pub target_um: Option<[f64; 2]>,
    /// A baseline instead of the configured policy.
    pub baseline: Option<Baseline>,
    /// A snapshot file instead of the configured policy.
    pub snapshot: Option<PathBuf>,
}

/// Runs the episodes and prints a line for each; a learner's snapshot is
/// fetched as `security` says.
pub fn run(config: &AgentConfig, args: RunArgs, security: Option<&Security>) -> anyhow::Result<()> {
    init_logging(false);
    if !args.twin && args.target_um.is_none() {
        bail!("on the instrument, give the target: --target-um DX,DY");
    }
    let mut policy = match (args.baseline, args.snapshot) {
        (Some(baseline), _) => LoadedPolicy::baseline(baseline, &config.env),
        (None, Some(file)) => {
            LoadedPolicy::choose(&PolicyChoice::File(file), &config.policy, &config.env, None)?
        }
        (None, None) => LoadedPolicy::load(&config.policy, &config.env, security)?,
    };
    tracing::info!(policy = %policy.description, "policy loaded");
    let mut instrument = Instrument::open(config, args.twin)?;
    let halt = Halt::default();
    let stopper = instrument.rig().stopper();
    let signals = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot watch for signals")?;
    let mut stop = StopSignals::install(signals.handle())?;
    std::thread::spawn({
        let halt = halt.clone();
        move || {
            let name = signals.block_on(stop.recv());
            tracing::warn!("{name}: stopping the episode");
            // A signal is an operator's stop: a profiled stop as the loop
            // ends; an immediate one too if the loop is stuck.
            halt.request(HaltKind::Stop);
            std::thread::sleep(std::time::Duration::from_secs(1));
            let _ = stopper.stop_now();
        }
    });
    let records = &config.records.dir;
    let px_per_um = config.stages.px_per_um;
    for k in 0..args.episodes {
        let seed = args.seed + k;
        let twin_target = instrument.start_twin_episode(seed);
        let target = match (args.target_um, twin_target) {
            (Some([x, y]), _) => [x * px_per_um, y * px_per_um],
            (None, Some(t)) => t,
            (None, None) => unreachable!("checked above"),
        };
        let header = EpisodeHeader {
            episode: k + 1,
            policy: policy.description.clone(),
            policy_version: policy.version,
            target_offset_px: target,
            rate_hz: config.control.rate_hz,
            twin_seed: args.twin.then_some(seed),
        };
        let (summary, files) =
            instrument.run_recorded(&mut policy, &header, records, &halt, |_| {})?;
        let line = json!({
            "episode": header.episode,
            "twin_seed": header.twin_seed,
            "summary": summary,
            "twin_truth": instrument.twin_truth(&summary),
            "files": files,
        });
        println!("{line}");
        if halt.pending().is_some() {
            break;
        }
    }
    Ok(())
}
