//! The hardware agent's Prometheus metrics: what its status shows, read at
//! each scrape, step and episode counters, the camera's frame counters,
//! and the loop's latency.

use super::state::{DaemonState, State};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use tweezer_rpc::{MetricSample, Prometheus};
use tweezer_vision::FrameCounters;

/// The metrics of the agent whose state is `shared` and whose camera
/// counts its frames in `frames`.
pub fn prometheus(shared: Arc<DaemonState>, frames: Arc<FrameCounters>) -> Prometheus {
    let mut metrics = Prometheus::new("tweezer_agent");
    metrics.histogram(
        "step_latency_seconds",
        "Seconds from a frame's capture to the stages' velocity command.",
        &shared.latency_seconds,
    );
    metrics.samples(move || {
        let status = shared.status().clone();
        let state = |s: State| f64::from(u8::from(status.state() == s));
        let [delivered, incomplete, dropped] = frames.read();
        vec![
            MetricSample::counter(
                "camera_frames",
                "Frames a live camera handed to segmentation.",
                delivered,
            ),
            MetricSample::counter(
                "camera_incomplete_frames",
                "Frames that arrived incomplete or malformed, kept from segmentation.",
                incomplete,
            ),
            MetricSample::counter(
                "camera_dropped_frames",
                "Frames triggered by software that never arrived.",
                dropped,
            ),
            MetricSample::counter("episodes", "Episodes started.", status.episode),
            MetricSample::counter(
                "steps",
                "Control steps run.",
                shared.steps.load(Ordering::Relaxed),
            ),
            MetricSample::counter(
                "successes",
                "Episodes that reached the target.",
                shared.successes.load(Ordering::Relaxed),
            ),
            MetricSample::counter(
                "collisions",
                "Episodes that ended in a collision.",
                shared.collisions.load(Ordering::Relaxed),
            ),
            MetricSample::gauge("idle", "1 while idle.", state(State::Idle)),
            MetricSample::gauge("running", "1 while an episode runs.", state(State::Running)),
            MetricSample::gauge(
                "emergency_stopped",
                "1 while an emergency stop is in force.",
                state(State::EmergencyStopped),
            ),
            MetricSample::gauge(
                "fault",
                "1 after a fault, until reset.",
                state(State::Fault),
            ),
            MetricSample::gauge("stage_x_mm", "Stage X position, mm.", status.stage_mm[0]),
            MetricSample::gauge("stage_y_mm", "Stage Y position, mm.", status.stage_mm[1]),
            MetricSample::gauge(
                "policy_version",
                "Version of the policy's snapshot (0: not a learner's).",
                status.policy_version as f64,
            ),
            MetricSample::gauge(
                "period_seconds",
                "Mean control period of the current or last episode.",
                status.period_ms / 1e3,
            ),
            MetricSample::gauge(
                "detections",
                "Spheres found in the last frame.",
                f64::from(status.detections),
            ),
            MetricSample::gauge(
                "virtual_obstacles",
                "Virtual obstacles in the overlay.",
                status.virtual_obstacles as f64,
            ),
        ]
    });
    metrics
}
