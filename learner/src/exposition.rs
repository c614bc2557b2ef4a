//! The learner's Prometheus metrics: what its status shows, read at each
//! scrape, and its latency histograms.

use crate::service::status;
use crate::shared::Shared;
use std::sync::Arc;
use tweezer_proto::pb;
use tweezer_rpc::{Figure, Prometheus};

/// The metrics of the learner whose state is `shared`.
pub fn prometheus(shared: Arc<Shared>) -> Prometheus {
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
    metrics.figures(move || figures(&status(&shared)));
    metrics
}

fn figures(s: &pb::LearnerStatus) -> Vec<Figure> {
    vec![
        Figure::counter(
            "steps_inserted",
            "Transitions stored in the replay buffer.",
            s.steps_inserted,
        ),
        Figure::counter("updates", "TD3 updates made.", s.updates),
        Figure::counter("episodes", "Episodes the actors finished.", s.episodes),
        Figure::counter(
            "malformed_batches",
            "Step batches refused as malformed.",
            s.malformed_batches,
        ),
        Figure::counter(
            "duplicate_batches",
            "Step batches dropped as already stored.",
            s.duplicate_batches,
        ),
        Figure::gauge(
            "buffer_size",
            "Transitions in the replay buffer.",
            s.buffer_size as f64,
        ),
        Figure::gauge(
            "buffer_capacity",
            "The replay buffer's capacity.",
            s.buffer_capacity as f64,
        ),
        Figure::gauge(
            "insert_rate",
            "Transitions stored per second, recently.",
            s.insert_rate,
        ),
        Figure::gauge(
            "sample_rate",
            "Transitions sampled per second, recently.",
            s.sample_rate,
        ),
        Figure::gauge(
            "connected_actors",
            "Open StreamSteps calls.",
            f64::from(s.connected_actors),
        ),
        Figure::gauge(
            "rolling_return",
            "Mean return of the recent episodes.",
            s.rolling_return,
        ),
        Figure::gauge(
            "success_rate",
            "Fraction of the recent episodes that reached the target.",
            s.success_rate,
        ),
        Figure::gauge(
            "latest_snapshot",
            "Version of the newest policy snapshot.",
            s.latest_snapshot as f64,
        ),
        Figure::gauge(
            "best_snapshot",
            "Version of the snapshot with the best rolling return.",
            s.best_snapshot as f64,
        ),
        Figure::gauge(
            "critic_loss",
            "Mean critic loss over the recent updates.",
            s.critic_loss,
        ),
        Figure::gauge(
            "actor_loss",
            "Mean actor loss over the recent updates.",
            s.actor_loss,
        ),
        Figure::gauge("mean_q", "Mean Q over the recent updates.", s.mean_q),
        Figure::gauge(
            "paused",
            "1 while an operator has paused learning.",
            f64::from(u8::from(s.paused)),
        ),
        Figure::gauge(
            "explore_uniformly",
            "1 while actors take uniformly random actions.",
            f64::from(u8::from(s.explore_uniformly)),
        ),
        Figure::gauge(
            "limiter_blocking_inserts",
            "1 while the rate limiter holds actors back.",
            f64::from(u8::from(s.limiter_state == "blocking inserts")),
        ),
        Figure::gauge(
            "limiter_waiting_for_data",
            "1 while updates wait for new transitions.",
            f64::from(u8::from(s.limiter_state == "waiting for data")),
        ),
    ]
}
