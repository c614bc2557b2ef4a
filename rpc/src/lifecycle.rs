//! A service process's life from its bound listeners to its exit, the same
//! for the learner and the hardware agent: the "listening" line its
//! launchers wait for, its metrics beside it, a stop signal or the
//! process's own end, and a bounded grace for clients to hang up.

use crate::{GrpcService, Prometheus, ServerSecurity};
use anyhow::Context;
use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tweezer_process::StopSignals;

/// A service's listeners, bound before anything else starts so that an
/// address in use is refused first.
#[derive(Debug)]
pub struct Listeners {
    grpc: TcpListener,
    metrics: Option<TcpListener>,
}

/// How a service ends: what a stop signal starts (for the log), what else
/// ends it, what stopping does, and how long clients then get.
pub struct Stopping<'a, E, F> {
    /// What the process does on a stop signal, as the log says it.
    pub on_signal: &'a str,
    /// Resolves when the process ends of its own accord (never, for one
    /// that serves until a signal).
    pub ends: E,
    /// Called once when stopping begins, whatever began it.
    pub then: F,
    /// How long clients may stay connected once stopping began.
    pub grace: Duration,
}

impl Listeners {
    /// Binds `listen` for gRPC, and `metrics_listen` when given; each is a
    /// config field's value and name, which a refusal names.
    pub async fn bind(
        listen: (SocketAddr, &str),
        metrics_listen: Option<(SocketAddr, &str)>,
    ) -> anyhow::Result<Self> {
        let grpc = bind(listen).await?;
        let metrics = match metrics_listen {
            Some(listen) => Some(bind(listen).await?),
            None => None,
        };
        Ok(Self { grpc, metrics })
    }

    /// The gRPC address bound.
    pub fn addr(&self) -> std::io::Result<SocketAddr> {
        self.grpc.local_addr()
    }

    /// Serves `service` secured by `security`, and `metrics` on the metrics
    /// listener, as process `name`, until a stop signal or `stopping.ends`;
    /// then clients get `stopping.grace` to hang up, and one that never
    /// does is cut off.
    pub async fn serve<S, E, F>(
        self,
        name: &str,
        security: ServerSecurity,
        service: S,
        metrics: Arc<Prometheus>,
        stopping: Stopping<'_, E, F>,
    ) -> anyhow::Result<()>
    where
        S: GrpcService,
        E: Future<Output = ()> + Send,
        F: FnOnce() + Send,
    {
        let Stopping {
            on_signal,
            ends,
            then,
            grace,
        } = stopping;
        let addr = self.addr()?;
        let mut signals = StopSignals::install(&tokio::runtime::Handle::current())?;
        tracing::info!(%addr, "{name} serving");
        println!("{name} listening on {addr}");
        let (stop, stopped) = tokio::sync::watch::channel(false);
        let until_stopped = move || {
            let mut stopped = stopped.clone();
            async move {
                let _ = stopped.wait_for(|&s| s).await;
            }
        };
        if let Some(listener) = self.metrics {
            let metrics_addr = listener.local_addr()?;
            tracing::info!(%metrics_addr, "Prometheus metrics at /metrics");
            let (security, done) = (security.clone(), until_stopped());
            tokio::spawn(async move { security.serve_metrics(listener, metrics, done).await });
        }
        let shutdown = async move {
            tokio::select! {
                signal = signals.recv() => tracing::info!(signal, "stopping: {on_signal}"),
                () = ends => {}
            }
            then();
            stop.send_replace(true);
        };
        let server = security.serve(self.grpc, service, shutdown);
        let grace = async {
            until_stopped().await;
            tokio::time::sleep(grace).await;
            tracing::warn!("closing connections still open after the shutdown grace period");
        };
        tokio::select! {
            served = server => served,
            () = grace => Ok(()),
        }
    }
}

/// Binds `addr`, the value of config field `field`.
async fn bind((addr, field): (SocketAddr, &str)) -> anyhow::Result<TcpListener> {
    (TcpListener::bind(addr).await).with_context(|| format!("cannot listen on {addr} ({field})"))
}
