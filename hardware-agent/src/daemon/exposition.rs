//! The hardware agent's Prometheus metrics: what its status shows, read at
//! each scrape, step and episode counters, and the loop's latency.

use super::status::{Shared, State};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use tweezer_rpc::{Figure, Prometheus};

/// The metrics of the agent whose state is `shared`.
pub fn prometheus(shared: Arc<Shared>) -> Prometheus {
    let mut metrics = Prometheus::new("tweezer_agent");
    metrics.histogram(
        "step_latency_seconds",
        "Seconds from a frame's capture to the stages' velocity command.",
        &shared.latency_seconds,
    );
    metrics.figures(move || {
        let status = shared.status().clone();
        let state = |s: State| f64::from(u8::from(status.state == s));
        vec![
            Figure::counter("episodes", "Episodes started.", status.episode),
            Figure::counter(
                "steps",
                "Control steps run.",
                shared.steps.load(Ordering::Relaxed),
            ),
            Figure::counter(
                "successes",
                "Episodes that reached the target.",
                shared.successes.load(Ordering::Relaxed),
            ),
            Figure::counter(
                "collisions",
                "Episodes that ended in a collision.",
                shared.collisions.load(Ordering::Relaxed),
            ),
            Figure::gauge("idle", "1 while idle.", state(State::Idle)),
            Figure::gauge("running", "1 while an episode runs.", state(State::Running)),
            Figure::gauge(
                "emergency_stopped",
                "1 while an emergency stop is in force.",
                state(State::EmergencyStopped),
            ),
            Figure::gauge(
                "fault",
                "1 after a fault, until reset.",
                state(State::Fault),
            ),
            Figure::gauge("stage_x_mm", "Stage X position, mm.", status.stage_mm[0]),
            Figure::gauge("stage_y_mm", "Stage Y position, mm.", status.stage_mm[1]),
            Figure::gauge(
                "policy_version",
                "Version of the policy's snapshot (0: not a learner's).",
                status.policy_version as f64,
            ),
            Figure::gauge(
                "period_seconds",
                "Mean control period of the current or last episode.",
                status.period_ms / 1e3,
            ),
            Figure::gauge(
                "detections",
                "Spheres found in the last frame.",
                f64::from(status.detections),
            ),
            Figure::gauge(
                "virtual_obstacles",
                "Virtual obstacles in the overlay.",
                status.virtual_obstacles as f64,
            ),
        ]
    });
    metrics
}
