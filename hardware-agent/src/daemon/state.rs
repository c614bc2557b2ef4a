//! What the service and the control thread share: the status, the halt
//! request, the stopper and the telemetry feed, in domain types.

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

/// What the agent is doing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum State {
    Idle,
    Running,
    EmergencyStopped,
    Fault,
    Loading,
}

/// One telemetry message: a step of an episode, or its end.
#[derive(Clone, Debug, PartialEq)]
pub enum Telemetry {
    /// A step taken.
    Step {
        /// The episode's number.
        episode: u64,
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
    pub state: State,
    pub episode: u64,
    pub step: u32,
    pub stage_mm: [f64; 2],
    pub last_ending: Option<Ending>,
    pub policy_version: u64,
    pub policy: String,
    pub period_ms: f64,
    pub message: String,
    pub detections: u32,
    pub latency_ms: f64,
    pub virtual_obstacles: usize,
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
                state: State::Idle,
                episode: 0,
                step: 0,
                stage_mm: [0.0; 2],
                last_ending: None,
                policy_version: policy.version,
                policy: policy.description.clone(),
                period_ms: 0.0,
                message: String::new(),
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
    /// job at a time, none while an emergency stop is in force.
    pub fn claim(&self, to: State) -> Result<(), String> {
        let mut status = self.status();
        if let Some(HaltKind::Emergency(reason)) = self.halt.pending() {
            return Err(format!(
                "emergency stop in force ({reason}); reset it first"
            ));
        }
        if status.state != State::Idle {
            let why = if status.message.is_empty() {
                String::new()
            } else {
                format!(": {}", status.message)
            };
            return Err(format!("the agent is {:?}{why}", status.state));
        }
        status.state = to;
        Ok(())
    }

    pub fn status(&self) -> MutexGuard<'_, Status> {
        self.status.lock().unwrap_or_else(|p| p.into_inner())
    }
}
