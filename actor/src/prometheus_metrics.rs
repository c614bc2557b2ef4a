//! The actor's Prometheus metrics: its report as of the last batch, and
//! the time to step its environments for a batch.

use crate::stream::RunReport;
use std::sync::{Arc, Mutex};
use tweezer_rpc::{Histogram, MetricSample, Prometheus};

/// The metrics of an actor whose report is published in `report`.
pub fn prometheus(report: Arc<Mutex<RunReport>>, batch_seconds: &Histogram) -> Prometheus {
    let mut metrics = Prometheus::new("tweezer_actor");
    metrics.histogram(
        "batch_seconds",
        "Seconds to step the environments for one batch of transitions.",
        batch_seconds,
    );
    metrics.samples(move || {
        let r = report.lock().unwrap_or_else(|p| p.into_inner()).clone();
        vec![
            MetricSample::counter(
                "steps_acked",
                "Transitions the learner acknowledged.",
                r.steps_acked,
            ),
            MetricSample::counter(
                "batches_sent",
                "Batches sent, resends included.",
                r.batches_sent,
            ),
            MetricSample::counter(
                "reconnects",
                "Connections to the learner after the first.",
                r.reconnects,
            ),
            MetricSample::counter("episodes", "Episodes finished.", r.episodes),
            MetricSample::gauge(
                "mean_return",
                "Mean return of the finished episodes.",
                r.mean_return,
            ),
            MetricSample::gauge(
                "success_rate",
                "Fraction of the finished episodes that reached the target.",
                r.success_rate,
            ),
            MetricSample::gauge(
                "batches_unacknowledged",
                "Batches sent and not yet acknowledged.",
                r.batches_unacknowledged as f64,
            ),
            MetricSample::gauge(
                "snapshot_version",
                "Version of the learner's snapshot acting (0: none yet).",
                r.snapshots_loaded.last().copied().unwrap_or(0) as f64,
            ),
        ]
    });
    metrics
}
