//! `hardware-agent home`: homes both stages once after their controllers
//! power up (until then `run` and `serve` refuse to drive them), parks
//! them mid-travel, and prints one JSON line with where and which
//! controllers.

use kdc101::{StagePair, StagesConfig};
use serde_json::json;
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_process::init_logging;

/// Homes and parks the configured stages. SIGINT or SIGTERM stops both
/// motors at once and ends the process.
pub fn run(config: &AgentConfig) -> anyhow::Result<()> {
    init_logging(false);
    let homing = StagesConfig {
        require_homed: false,
        ..config.stages.clone()
    };
    let (mut stages, info) = StagePair::open(&homing, config.control.command_interval())?;
    super::stop_stages_on_signal(stages.stopper(), "homing")?;
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
