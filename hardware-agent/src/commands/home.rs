//! `hardware-agent home`: homes both stages once after their controllers
//! power up (until then `run` and `serve` refuse to drive them), parks
//! them mid-travel, and prints one JSON line with where and which
//! controllers.

use anyhow::Context;
use kdc101::{StagePair, StagesConfig};
use serde_json::json;
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_process::{StopSignals, init_logging};

/// Homes and parks the configured stages. SIGINT or SIGTERM stops both
/// motors at once and ends the process.
pub fn run(config: &AgentConfig) -> anyhow::Result<()> {
    init_logging(false);
    let homing = StagesConfig {
        require_homed: false,
        ..config.stages.clone()
    };
    let (mut stages, info) = StagePair::open(&homing, config.control.command_interval())?;
    let stopper = stages.stopper();
    let signals = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot watch for signals")?;
    let mut stop = StopSignals::install(signals.handle())?;
    std::thread::spawn(move || {
        let name = signals.block_on(stop.recv());
        let stopped = stopper.stop_now();
        tracing::warn!(
            ?stopped,
            "{name}: both stages stopped before homing finished"
        );
        std::process::exit(130);
    });
    tracing::info!(
        x = info[0].serial,
        y = info[1].serial,
        "homing stage X, then stage Y: each runs to its home limit switch"
    );
    let parked = stages.home()?;
    let line = json!({
        "homed": true,
        "parked_mm": parked,
        "x_serial": info[0].serial,
        "y_serial": info[1].serial,
    });
    println!("{line}");
    let serials = [
        ("x_serial", config.stages.x_serial, &info[0]),
        ("y_serial", config.stages.y_serial, &info[1]),
    ];
    for (field, configured, found) in serials {
        if configured.is_none() {
            tracing::warn!(
                "stages.{field} is not set: add `{field} = {}` under [stages] so that swapped \
                 ports are refused",
                found.serial
            );
        }
    }
    Ok(())
}
