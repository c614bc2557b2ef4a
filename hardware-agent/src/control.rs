//! The control loop of the physical and augmented environments (`docs/spec.md`
//! §5–6): frame → segmentation → the trapped sphere and the free ones →
//! observation (free spheres, virtual obstacles and the target vector from the
//! stage positions) → policy → stage velocities, at a fixed rate, under a
//! watchdog. The episode is scored as the virtual environment scores it.

mod halt;
mod rig;
mod watchdog;

pub use halt::{Halt, HaltKind};
pub use rig::{Rig, RigError};
pub use watchdog::Watchdog;

use serde::{Deserialize, Serialize};
use tweezer_config::{ConfigError, in_range};
use tweezer_gym::Outcome;

/// The `[control]` table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ControlConfig {
    /// Control steps per second (the paper's stages allow about 4).
    pub rate_hz: f64,
    /// The watchdog stops the stages when a step starts this late, ms.
    pub deadline_margin_ms: f64,
    /// Trap travel per step at action ±1 along each axis, px (the virtual
    /// environment's stage speed, so a step moves as far as in training).
    pub px_per_step: f64,
    /// The trapped sphere is the detection nearest the FOV centre within
    /// this distance, px.
    pub trap_search_px: f64,
    /// The episode ends when the trapped sphere is missing from this many
    /// frames in a row (the stages hold still meanwhile).
    pub lost_trap_frames: u32,
}

impl Default for ControlConfig {
    fn default() -> Self {
        Self {
            rate_hz: 4.0,
            deadline_margin_ms: 100.0,
            px_per_step: 10.0,
            trap_search_px: 27.0,
            lost_trap_frames: 2,
        }
    }
}

impl ControlConfig {
    /// Checks every field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        for (name, value, lo, hi) in [
            ("rate_hz", self.rate_hz, 0.1, 100.0),
            ("deadline_margin_ms", self.deadline_margin_ms, 1.0, 10_000.0),
            ("px_per_step", self.px_per_step, 0.01, 1000.0),
            ("trap_search_px", self.trap_search_px, 1.0, 500.0),
        ] {
            in_range(name, value, lo, hi)?;
        }
        if !(1..=100).contains(&self.lost_trap_frames) {
            return Err(ConfigError::invalid(
                "lost_trap_frames",
                format!("{} must lie in [1, 100]", self.lost_trap_frames),
            ));
        }
        Ok(())
    }

    /// The control period, s.
    pub fn period_s(&self) -> f64 {
        1.0 / self.rate_hz
    }

    /// The longest time between two commands to the stages: a period and
    /// the deadline margin.
    pub fn command_interval(&self) -> std::time::Duration {
        std::time::Duration::from_secs_f64(self.period_s() + self.deadline_margin_ms / 1000.0)
    }
}

/// How an episode ended.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(rename_all = "snake_case", tag = "ending", content = "reason")]
pub enum Ending {
    /// The trap reached the target.
    Success,
    /// A free sphere (or virtual obstacle) entered the trap region.
    Collision,
    /// The time limit passed.
    Timeout,
    /// An operator stopped it.
    Stopped,
    /// An emergency stop ended it.
    EmergencyStopped(String),
    /// The trapped sphere was no longer seen at the trap.
    TrapLost,
    /// A device, the camera or the loop's timing failed.
    Fault(String),
}

impl Ending {
    /// The virtual environment's outcome this corresponds to, if any.
    pub fn outcome(&self) -> Option<Outcome> {
        match self {
            Self::Success => Some(Outcome::Success),
            Self::Collision => Some(Outcome::Collision),
            Self::Timeout => Some(Outcome::Timeout),
            _ => None,
        }
    }
}

/// One control step, as records and telemetry keep it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StepLog {
    /// Steps taken before this one.
    pub step: u32,
    /// Seconds since the episode started.
    pub time_s: f64,
    /// What the policy saw: the free spheres detected, then the virtual
    /// obstacles in view (FOV px).
    pub centres: Vec<[f32; 2]>,
    /// Each centre's move since the previous frame relative to the sample,
    /// px, matched from consecutive frames; `None` for one new to the view.
    pub displacements: Vec<Option<[f32; 2]>>,
    /// How many of `centres` are detections (the rest are virtual).
    pub detected: usize,
    /// Where the trapped sphere was seen (FOV px).
    pub trapped: [f32; 2],
    /// The target vector.
    pub vector: [f32; 2],
    /// The action chosen.
    pub action: [f32; 2],
    /// The trap's position relative to where the stages were connected,
    /// world px.
    pub position_px: [f64; 2],
    /// The stage carriages (X, Y), mm.
    pub stage_mm: [f64; 2],
    /// Frame in to command out, ms: from the frame's arrival at this
    /// computer where the camera says (a GenICam buffer's timestamp), else
    /// from the end of the grab; segmentation, observation, policy, stage
    /// commands.
    pub latency_ms: f64,
    /// Of that, the policy, ms.
    pub policy_ms: f64,
}

/// Timing of the loop over an episode.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct LoopTiming {
    /// Median frame-to-command latency, ms.
    pub latency_ms_median: f64,
    /// Its 99th percentile, ms.
    pub latency_ms_p99: f64,
    /// Its maximum, ms.
    pub latency_ms_max: f64,
    /// Mean time between steps, ms.
    pub period_ms_mean: f64,
}

impl LoopTiming {
    /// Figures of these latencies (ms) over `elapsed_s` and `steps`.
    pub fn of(latencies: &mut [f64], elapsed_s: f64, steps: u32) -> Self {
        if latencies.is_empty() {
            return Self::default();
        }
        latencies.sort_by(f64::total_cmp);
        let at = |q: f64| latencies[((latencies.len() - 1) as f64 * q).round() as usize];
        Self {
            latency_ms_median: at(0.5),
            latency_ms_p99: at(0.99),
            latency_ms_max: latencies[latencies.len() - 1],
            period_ms_mean: 1000.0 * elapsed_s / f64::from(steps.max(1)),
        }
    }
}

/// What an episode did.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EpisodeSummary {
    /// How it ended.
    #[serde(flatten)]
    pub ending: Ending,
    /// Actions taken.
    pub steps: u32,
    /// Seconds from start to end.
    pub duration_s: f64,
    /// Trap at the start, world px.
    pub start_px: [f64; 2],
    /// The target, world px.
    pub target_px: [f64; 2],
    /// Trap at the end, world px (the last position read).
    pub end_px: [f64; 2],
    /// Loop timing.
    pub timing: LoopTiming,
}
