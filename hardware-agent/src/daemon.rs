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

use anyhow::Context;
use control_thread::{ControlThread, Job};
use service::AgentService;
use state::DaemonState;
use std::sync::Arc;
use tokio::net::TcpListener;
use tweezer_gym::Baseline;
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_hardware_agent::control::HaltKind;
use tweezer_hardware_agent::instrument::Instrument;
use tweezer_hardware_agent::policy_source::{LoadedPolicy, PolicyChoice};
use tweezer_process::{StopSignals, init_logging};
use tweezer_proto::pb::hardware_agent_server::HardwareAgentServer;
use tweezer_rpc::{Security, ServerSecurity};

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
        let listener = TcpListener::bind(config.service.listen)
            .await
            .with_context(|| {
                format!(
                    "cannot listen on {} (service.listen)",
                    config.service.listen
                )
            })?;
        let addr = listener.local_addr()?;
        let metrics =
            match config.service.metrics_listen {
                Some(listen) => Some(TcpListener::bind(listen).await.with_context(|| {
                    format!("cannot listen on {listen} (service.metrics_listen)")
                })?),
                None => None,
            };
        let mut signals = StopSignals::install(&tokio::runtime::Handle::current())?;
        tracing::info!(%addr, twin, "hardware agent serving");
        println!("hardware-agent listening on {addr}");
        let (stopping, mut stopped) = tokio::sync::watch::channel(false);
        if let Some(listener) = metrics {
            let metrics_addr = listener.local_addr()?;
            tracing::info!(%metrics_addr, "Prometheus metrics at /metrics");
            let security = listener_security.clone();
            let registry = Arc::new(prometheus_metrics::prometheus(
                shared.clone(),
                frames.clone(),
            ));
            let mut done = stopped.clone();
            tokio::spawn(async move {
                let shutdown = async move {
                    let _ = done.wait_for(|&s| s).await;
                };
                security.serve_metrics(listener, registry, shutdown).await;
            });
        }
        let service = AgentService::new(shared.clone(), jobs.clone());
        let shutdown = async move {
            let signal = signals.recv().await;
            tracing::info!(
                signal,
                "stopping: ending the episode and stopping the stages"
            );
            let _ = stopping.send(true);
        };
        let server = listener_security.serve(listener, HardwareAgentServer::new(service), shutdown);
        // Clients get a grace period to hang up; a telemetry subscriber
        // that never does must not keep the agent alive.
        let grace = async {
            let _ = stopped.wait_for(|&s| s).await;
            tokio::time::sleep(SHUTDOWN_GRACE).await;
            tracing::warn!("closing connections still open after the shutdown grace period");
        };
        tokio::select! {
            served = server => served,
            () = grace => Ok(()),
        }
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
