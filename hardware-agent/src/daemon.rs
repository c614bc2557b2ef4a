//! `hardware-agent serve`: the daemon on the microscope PC. The instrument
//! (or its twin) is driven by a control thread that owns it; the gRPC
//! service reads the shared status, hands the thread jobs (start an
//! episode, load a policy, set the overlay) and stops the stages itself on
//! an emergency stop, without waiting for the loop.

mod control_thread;
mod follower;
mod prometheus_metrics;
mod service;
mod state;

use control_thread::{ControlThread, Job};
use service::AgentService;
use state::DaemonState;
use std::sync::Arc;
use tweezer_gym::Baseline;
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_hardware_agent::control::HaltKind;
use tweezer_hardware_agent::instrument::Instrument;
use tweezer_hardware_agent::policy_source::{LoadedPolicy, PolicyChoice};
use tweezer_process::init_logging;
use tweezer_proto::pb::hardware_agent_server::HardwareAgentServer;
use tweezer_rpc::{Listeners, Security, ServerSecurity, Stopping};

/// How long clients may stay connected after a stop signal.
const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(2);

/// Serves until SIGINT or SIGTERM, secured as `security` says; the stages
/// are stopped on the way out.
pub fn serve(
    config: AgentConfig,
    security: Security,
    twin: bool,
    baseline: Option<Baseline>,
    json_logs: bool,
) -> anyhow::Result<()> {
    init_logging(json_logs);
    let listener_security = ServerSecurity::load(&security)?;
    let policy = match baseline {
        Some(baseline) => LoadedPolicy::baseline(baseline, &config.env),
        None => LoadedPolicy::load(&config.policy, &config.env, Some(&security))?,
    };
    tracing::info!(policy = %policy.description, "policy loaded");
    let mut instrument = Instrument::open(&config, twin)?;
    let stopper = instrument.rig().stopper();
    let frames = instrument.frame_counters();
    let shared = Arc::new(DaemonState::new(stopper, &policy, instrument.overlay_len()));
    let follow = match config.policy.choice()? {
        PolicyChoice::Follow(tag) if baseline.is_none() => Some(tag),
        _ => None,
    };
    let (jobs, thread) = ControlThread::spawn(
        instrument,
        policy,
        follow,
        config.clone(),
        security,
        shared.clone(),
    )?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let served = runtime.block_on(async {
        let listeners = Listeners::bind(
            (config.service.listen, "service.listen"),
            (config.service.metrics_listen).map(|listen| (listen, "service.metrics_listen")),
        )
        .await?;
        tracing::info!(twin, "instrument ready");
        let service = HardwareAgentServer::new(AgentService::new(shared.clone(), jobs.clone()));
        let metrics = Arc::new(prometheus_metrics::prometheus(shared.clone(), frames));
        // Telemetry subscribers that never hang up must not keep the agent
        // alive past the grace.
        let stopping = Stopping {
            on_signal: "ending the episode and stopping the stages",
            ends: std::future::pending(),
            then: || {},
            grace: SHUTDOWN_GRACE,
        };
        listeners
            .serve(
                "hardware-agent",
                listener_security,
                service,
                metrics,
                stopping,
            )
            .await
    });
    // Whatever ended the service, the episode ends and the motors stop.
    shared.halt.request(HaltKind::Stop);
    let _ = jobs.send(Job::Quit);
    drop(jobs);
    if thread.join().is_err() {
        let _ = shared.stopper.stop_now();
        anyhow::bail!("the control thread panicked (the stages were stopped)");
    }
    served
}
