//! What the service and the control thread share: the status, the halt
//! request, the stopper and the telemetry feed, in domain types.
//!
//! The daemon's state is two parts, changed only by the transitions here:
//! what it is doing ([`Activity`]: one job at a time) and what blocks new
//! jobs until an operator resets it ([`Latch`]: an emergency stop, or a
//! fault). A job ending never touches the latch, so an emergency stop that
//! arrives during a policy load or an overlay change stays in force; the
//! reported [`State`] is derived from both.

use kdc101::Stopper;
use serialport::TTYPort;
use std::sync::atomic::AtomicU64;
use std::sync::{Mutex, MutexGuard};
use tokio::sync::broadcast;
use tweezer_gym::{Action, Observation};
use tweezer_hardware_agent::control::{Ending, Halt, HaltKind};
use tweezer_hardware_agent::policy_source::LoadedPolicy;
use tweezer_rpc::{Histogram, latency_buckets};

/// Telemetry messages kept for a slow subscriber before it skips ahead.
const TELEMETRY_BACKLOG: usize = 256;

/// The agent's state as reported: a latch outranks the activity.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum State {
    Idle,
    Running,
    EmergencyStopped,
    Fault,
    Loading,
}

/// What the agent is doing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activity {
    Idle,
    /// An episode runs.
    Running,
    /// A policy or an overlay is being loaded.
    Loading,
}

/// What blocks new jobs until ResetEmergencyStop.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Latch {
    Clear,
    /// An emergency stop, with its reason.
    EmergencyStop(String),
    /// An episode ended in a fault, with what went wrong.
    Fault(String),
}

/// One telemetry message: a step of an episode, or its end.
#[derive(Clone, Debug, PartialEq)]
pub enum Telemetry {
    /// A step taken.
    Step {
        /// The episode's number.
        episode: u64,
        /// The version of the policy driving it.
        policy_version: u64,
        /// The step's index in the episode.
        step: u32,
        /// Seconds since the episode started.
        time_s: f64,
        /// What the policy saw.
        observation: Observation,
        /// What it commanded.
        action: Action,
        /// The stages' positions (X, Y), mm.
        stage_mm: [f64; 2],
        /// Frame capture to the stages' command, ms.
        latency_ms: f64,
    },
    /// The episode ended.
    End {
        /// The episode's number.
        episode: u64,
        /// The version of the policy that drove it.
        policy_version: u64,
        /// Steps it took.
        steps: u32,
        /// Its duration, s.
        time_s: f64,
        /// How it ended.
        ending: Ending,
    },
}

/// The agent's status, in domain terms.
#[derive(Clone, Debug)]
pub struct Status {
    pub activity: Activity,
    pub latch: Latch,
    pub episode: u64,
    pub step: u32,
    pub stage_mm: [f64; 2],
    pub last_ending: Option<Ending>,
    pub policy_version: u64,
    pub policy: String,
    /// The learner's tag followed ("best", "latest"); empty if none.
    pub following: String,
    pub period_ms: f64,
    pub detections: u32,
    pub latency_ms: f64,
    pub virtual_obstacles: usize,
}

impl Status {
    /// The state to report.
    pub fn state(&self) -> State {
        match (&self.latch, self.activity) {
            (Latch::EmergencyStop(_), _) => State::EmergencyStopped,
            (Latch::Fault(_), _) => State::Fault,
            (Latch::Clear, Activity::Running) => State::Running,
            (Latch::Clear, Activity::Loading) => State::Loading,
            (Latch::Clear, Activity::Idle) => State::Idle,
        }
    }

    /// Why the agent is stopped or in fault; empty otherwise.
    pub fn message(&self) -> &str {
        match &self.latch {
            Latch::EmergencyStop(reason) | Latch::Fault(reason) => reason,
            Latch::Clear => "",
        }
    }
}

/// Shared between the service and the control thread.
pub struct DaemonState {
    status: Mutex<Status>,
    pub halt: Halt,
    pub stopper: Stopper<TTYPort>,
    pub telemetry: broadcast::Sender<Telemetry>,
    /// Seconds from a frame's capture to the stages' command, per step.
    pub latency_seconds: Histogram,
    /// Steps run, all episodes together.
    pub steps: AtomicU64,
    /// Episodes that reached the target.
    pub successes: AtomicU64,
    /// Episodes that ended in a collision.
    pub collisions: AtomicU64,
}

impl DaemonState {
    pub fn new(stopper: Stopper<TTYPort>, policy: &LoadedPolicy, virtual_obstacles: usize) -> Self {
        Self {
            status: Mutex::new(Status {
                activity: Activity::Idle,
                latch: Latch::Clear,
                episode: 0,
                step: 0,
                stage_mm: [0.0; 2],
                last_ending: None,
                policy_version: policy.version,
                policy: policy.description.clone(),
                following: String::new(),
                period_ms: 0.0,
                detections: 0,
                latency_ms: 0.0,
                virtual_obstacles,
            }),
            halt: Halt::default(),
            stopper,
            telemetry: broadcast::channel(TELEMETRY_BACKLOG).0,
            latency_seconds: Histogram::new(latency_buckets()),
            steps: AtomicU64::new(0),
            successes: AtomicU64::new(0),
            collisions: AtomicU64::new(0),
        }
    }

    /// Moves the agent from idle to `to` for a job, or says why not: one
    /// job at a time, none while a latch is set.
    pub fn claim(&self, to: Activity) -> Result<(), String> {
        let mut status = self.status();
        match &status.latch {
            Latch::EmergencyStop(reason) => {
                return Err(format!(
                    "emergency stop in force ({reason}); reset it first"
                ));
            }
            Latch::Fault(reason) => {
                return Err(format!("the agent is in fault ({reason}); reset it first"));
            }
            Latch::Clear => {}
        }
        if status.activity != Activity::Idle {
            return Err(format!("the agent is busy ({:?})", status.activity));
        }
        status.activity = to;
        Ok(())
    }

    /// A job ended: the agent is idle again; the latch stays as it is.
    pub fn job_done(&self) {
        self.status().activity = Activity::Idle;
    }

    /// An episode ended with `ending` (`Err`: it could not run to an end):
    /// the agent is idle and says how the episode ended, in one change, so
    /// that no status shows the one without the other.
    pub fn episode_done(&self, ending: &Result<Ending, String>) {
        let mut status = self.status();
        status.activity = Activity::Idle;
        status.last_ending = Some(ending.clone().unwrap_or_else(Ending::Fault));
        let latch = match ending {
            Ok(Ending::EmergencyStopped(reason)) => {
                // The watchdog's stop, or the operator's already latched.
                self.halt.request(HaltKind::Emergency(reason.clone()));
                Latch::EmergencyStop(reason.clone())
            }
            Ok(Ending::Fault(reason)) | Err(reason) => Latch::Fault(reason.clone()),
            Ok(Ending::TrapLost) => Latch::Fault("the trapped sphere was lost".into()),
            Ok(_) => return,
        };
        // An emergency stop outranks a fault and keeps its first reason.
        if !matches!(status.latch, Latch::EmergencyStop(_)) {
            status.latch = latch;
        }
    }

    /// Latches an emergency stop: the request first, so that the loop sees
    /// it after whatever command it is sending, then the motors, from
    /// here. Whatever the agent is doing, the stop stays in force until
    /// [`Self::reset`].
    pub fn emergency_stop(&self, reason: String) -> Result<(), String> {
        self.halt.request(HaltKind::Emergency(reason.clone()));
        let sent = self.stopper.stop_now().map_err(|e| e.to_string());
        let mut status = self.status();
        let reason = match &sent {
            Ok(()) => reason,
            Err(e) => format!("{reason} (the stop could not be sent to a controller: {e})"),
        };
        status.latch = Latch::EmergencyStop(reason);
        sent
    }

    /// Clears a latched emergency stop or fault, or says why not: not while
    /// an episode is still ending.
    pub fn reset(&self) -> Result<(), String> {
        let mut status = self.status();
        if status.activity == Activity::Running {
            return Err("an episode is running: stop it first".into());
        }
        self.halt.clear();
        status.latch = Latch::Clear;
        Ok(())
    }

    pub fn status(&self) -> MutexGuard<'_, Status> {
        self.status.lock().unwrap_or_else(|p| p.into_inner())
    }
}
