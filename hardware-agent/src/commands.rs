//! The command line's one-shot commands; `serve` is the daemon (`daemon`).

pub mod bench;
pub mod calibrate;
pub mod cameras;
pub mod home;
pub mod run;
pub mod segment;

use anyhow::Context;
use kdc101::Stopper;
use serialport::TTYPort;
use tweezer_process::StopSignals;

/// From now on SIGINT or SIGTERM stops both motors at once and ends the
/// process (status 130), logging that `what` was cut short: a velocity
/// command would otherwise keep a stage moving.
pub fn stop_stages_on_signal(stopper: Stopper<TTYPort>, what: &'static str) -> anyhow::Result<()> {
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
            "{name}: both stages stopped before {what} finished"
        );
        std::process::exit(130);
    });
    Ok(())
}
