//! The learner's Prometheus metrics: what its status shows, read at each
//! scrape, and its latency histograms.

use crate::ingest::limiter::LimiterState;
use crate::ingest::status::LearnerStatus;
use crate::state::LearnerState;
use std::sync::Arc;
use tweezer_rpc::{MetricSample, Prometheus};

/// The metrics of the learner whose state is `shared`.
pub fn prometheus(shared: Arc<LearnerState>) -> Prometheus {
    let mut metrics = Prometheus::new("tweezer_learner");
    let timings = shared.timings();
    metrics.histogram(
        "update_seconds",
        "Seconds per TD3 update (sampling, tensors, critic and actor steps).",
        &timings.update_seconds,
    );
    metrics.histogram(
        "batch_seconds",
        "Seconds from a step batch's arrival to its acknowledgement, rate-limiter waits included.",
        &timings.batch_seconds,
    );
    metrics.samples(move || samples(&shared.status()));
    metrics
}

fn samples(s: &LearnerStatus) -> Vec<MetricSample> {
    vec![
        MetricSample::counter(
            "steps_inserted",
            "Transitions stored in the replay buffer.",
            s.steps_inserted,
        ),
        MetricSample::counter("updates", "TD3 updates made.", s.training.updates),
        MetricSample::counter("episodes", "Episodes the actors finished.", s.episodes),
        MetricSample::counter(
            "malformed_batches",
            "Step batches refused as malformed.",
            s.malformed_batches,
        ),
        MetricSample::counter(
            "diverged_updates",
            "Updates whose loss was not finite, undone by a rollback.",
            s.training.diverged_updates,
        ),
        MetricSample::counter(
            "checkpoint_failures",
            "Checkpoints that could not be written (a full disk, say); the learner goes on and retries.",
            s.training.checkpoint_failures,
        ),
        MetricSample::counter(
            "snapshot_failures",
            "Snapshots that could not be published; the learner goes on.",
            s.training.snapshot_failures,
        ),
        MetricSample::counter(
            "duplicate_batches",
            "Step batches dropped as already stored.",
            s.duplicate_batches,
        ),
        MetricSample::gauge(
            "buffer_size",
            "Transitions in the replay buffer.",
            s.buffer_size as f64,
        ),
        MetricSample::gauge(
            "buffer_capacity",
            "The replay buffer's capacity.",
            s.buffer_capacity as f64,
        ),
        MetricSample::gauge(
            "insert_rate",
            "Transitions stored per second, recently.",
            s.training.insert_rate,
        ),
        MetricSample::gauge(
            "sample_rate",
            "Transitions sampled per second, recently.",
            s.training.sample_rate,
        ),
        MetricSample::gauge(
            "connected_actors",
            "Open StreamSteps calls.",
            f64::from(s.connected_actors),
        ),
        MetricSample::gauge(
            "rolling_return",
            "Mean return of the recent episodes.",
            s.rolling.mean_return,
        ),
        MetricSample::gauge(
            "success_rate",
            "Fraction of the recent episodes that reached the target.",
            s.rolling.success_rate,
        ),
        MetricSample::gauge(
            "latest_snapshot",
            "Version of the newest policy snapshot.",
            s.latest_snapshot as f64,
        ),
        MetricSample::gauge(
            "best_snapshot",
            "Version of the snapshot with the best rolling return.",
            s.best_snapshot as f64,
        ),
        MetricSample::gauge(
            "critic_loss",
            "Mean critic loss over the recent updates.",
            s.training.critic_loss,
        ),
        MetricSample::gauge(
            "actor_loss",
            "Mean actor loss over the recent updates.",
            s.training.actor_loss,
        ),
        MetricSample::gauge(
            "mean_q",
            "Mean Q over the recent updates.",
            s.training.mean_q,
        ),
        MetricSample::gauge(
            "paused",
            "1 while an operator has paused learning.",
            f64::from(u8::from(s.paused)),
        ),
        MetricSample::gauge(
            "explore_uniformly",
            "1 while actors take uniformly random actions.",
            f64::from(u8::from(s.explore_uniformly)),
        ),
        MetricSample::gauge(
            "limiter_blocking_inserts",
            "1 while the rate limiter holds actors back.",
            f64::from(u8::from(s.limiter == Some(LimiterState::BlockingInserts))),
        ),
        MetricSample::gauge(
            "limiter_waiting_for_data",
            "1 while updates wait for new transitions.",
            f64::from(u8::from(s.limiter == Some(LimiterState::WaitingForData))),
        ),
    ]
}
