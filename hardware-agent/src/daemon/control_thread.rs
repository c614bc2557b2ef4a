//! The thread that owns the instrument and the policy: it runs the jobs the
//! service hands it, one at a time, and keeps the shared status current.

use super::follower::Follower;
use super::state::{DaemonState, Telemetry};
use kdc101::apt::StopMode;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, Sender, channel};
use std::thread::JoinHandle;
use std::time::Instant;
use tokio::sync::oneshot;
use tweezer_gym::{Action, Observation};
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_hardware_agent::control::{Ending, StepLog};
use tweezer_hardware_agent::instrument::Instrument;
use tweezer_hardware_agent::overlay::OverlaySpec;
use tweezer_hardware_agent::policy_source::{
    LoadedPolicy, PolicyChoice, PolicyError, SnapshotChoice,
};
use tweezer_hardware_agent::record::EpisodeHeader;
use tweezer_rpc::Security;

/// Where an episode's target lies.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Target {
    /// Relative to the trap now, µm along the image axes.
    RelativeUm([f64; 2]),
    /// Stage positions (X, Y), mm.
    AbsoluteMm([f64; 2]),
}

/// Why a job was refused.
#[derive(Debug)]
pub enum JobError {
    /// Not now (the agent is busy, stopped or faulted).
    Refused(String),
    /// Never: the request is wrong.
    Invalid(String),
    /// Not now: something the agent needs (the learner) cannot be reached.
    Unreachable(String),
}

type Reply = oneshot::Sender<Result<(), JobError>>;

/// Work for the control thread.
pub enum Job {
    /// Start an episode; the reply comes once it is running.
    Start {
        target: Option<Target>,
        twin_seed: Option<u64>,
        reply: Reply,
    },
    /// Replace the policy.
    LoadPolicy { choice: PolicyChoice, reply: Reply },
    /// Replace the virtual obstacles.
    SetOverlay { spec: OverlaySpec, reply: Reply },
    /// Stop the stages and end the thread.
    Quit,
}

/// The thread's state.
pub struct ControlThread {
    instrument: Instrument,
    policy: LoadedPolicy,
    /// The learner's tag being followed, if one is.
    follower: Option<Follower>,
    config: AgentConfig,
    /// How learners' snapshots are fetched.
    security: Security,
    shared: Arc<DaemonState>,
}

impl ControlThread {
    /// Starts the thread, following the learner's `follow` tag if given;
    /// jobs go to the returned sender.
    pub fn spawn(
        instrument: Instrument,
        policy: LoadedPolicy,
        follow: Option<SnapshotChoice>,
        config: AgentConfig,
        security: Security,
        shared: Arc<DaemonState>,
    ) -> std::io::Result<(Sender<Job>, JoinHandle<()>)> {
        let (jobs, inbox) = channel();
        let follower = follow
            .map(|tag| {
                Follower::spawn(
                    tag,
                    policy.version,
                    config.policy.clone(),
                    config.env.clone(),
                    security.clone(),
                )
            })
            .transpose()?;
        shared.status().following = follow.map(|t| t.to_string()).unwrap_or_default();
        let mut thread = Self {
            instrument,
            policy,
            follower,
            config,
            security,
            shared,
        };
        let handle = std::thread::Builder::new()
            .name("control".into())
            .spawn(move || thread.run(inbox))?;
        Ok((jobs, handle))
    }

    fn run(&mut self, inbox: Receiver<Job>) {
        while let Ok(job) = inbox.recv() {
            match job {
                Job::Quit => break,
                Job::Start {
                    target,
                    twin_seed,
                    reply,
                } => self.start(target, twin_seed, reply),
                Job::LoadPolicy { choice, reply } => {
                    let result = self.load_policy(choice);
                    let _ = reply.send(result);
                }
                Job::SetOverlay { spec, reply } => {
                    let result = self.set_overlay(&spec);
                    let _ = reply.send(result);
                }
            }
        }
        if self
            .instrument
            .rig()
            .stages()
            .stop(StopMode::Profiled)
            .is_err()
        {
            let _ = self.shared.stopper.stop_now();
        }
    }

    /// Loads a policy; the service has claimed the agent (Loading). A
    /// policy loaded, of whatever kind, ends following the one before.
    fn load_policy(&mut self, choice: PolicyChoice) -> Result<(), JobError> {
        let loaded = LoadedPolicy::choose(
            &choice,
            &self.config.policy,
            &self.config.env,
            Some(&self.security),
        )
        .map_err(|e| match e {
            PolicyError::Learner { .. } => JobError::Unreachable(e.to_string()),
            _ => JobError::Invalid(e.to_string()),
        })
        .and_then(|policy| {
            let follower = match choice {
                PolicyChoice::Follow(tag) => Some(
                    Follower::spawn(
                        tag,
                        policy.version,
                        self.config.policy.clone(),
                        self.config.env.clone(),
                        self.security.clone(),
                    )
                    .map_err(|e| JobError::Refused(format!("cannot start following: {e}")))?,
                ),
                _ => None,
            };
            Ok((policy, follower))
        });
        if let Ok((policy, follower)) = &loaded {
            tracing::info!(policy = %policy.description, following = ?follower.as_ref().map(|f| f.tag().to_string()), "policy loaded");
            let mut status = self.shared.status();
            status.policy_version = policy.version;
            status.policy = policy.description.clone();
            status.following = follower
                .as_ref()
                .map(|f| f.tag().to_string())
                .unwrap_or_default();
        }
        self.shared.job_done();
        (self.policy, self.follower) = loaded?;
        Ok(())
    }

    /// Between episodes: the newer snapshot a follower has ready, if any,
    /// becomes the policy.
    fn take_followed(&mut self) {
        let Some(policy) = self.follower.as_ref().and_then(Follower::take) else {
            return;
        };
        tracing::info!(policy = %policy.description, "following: the next episode runs the newer snapshot");
        let mut status = self.shared.status();
        status.policy_version = policy.version;
        status.policy = policy.description.clone();
        drop(status);
        self.policy = policy;
    }

    /// Replaces the overlay; the service has claimed the agent (Loading).
    fn set_overlay(&mut self, spec: &OverlaySpec) -> Result<(), JobError> {
        let result = self
            .instrument
            .set_overlay(spec)
            .map_err(|e| JobError::Invalid(e.to_string()));
        self.shared.status().virtual_obstacles = self.instrument.overlay_len();
        self.shared.job_done();
        result
    }

    /// The target relative to the trap, px, checked against the travel.
    fn target_offset(
        &mut self,
        target: Option<Target>,
        twin_seed: Option<u64>,
    ) -> Result<[f64; 2], JobError> {
        let seeded = match twin_seed {
            Some(seed) => Some(self.instrument.start_twin_episode(seed).ok_or_else(|| {
                JobError::Invalid("twin_seed applies to the digital twin only".into())
            })?),
            None => None,
        };
        let px_per_um = self.config.stages.px_per_um;
        let stages = self.instrument.rig().stages();
        let now = stages
            .position_px()
            .map_err(|e| JobError::Refused(e.to_string()))?;
        let offset = match (target, seeded) {
            (Some(Target::RelativeUm([x, y])), _) => [x * px_per_um, y * px_per_um],
            (Some(Target::AbsoluteMm(mm)), _) => {
                let at = stages.px(mm);
                [at[0] - now[0], at[1] - now[1]]
            }
            (None, Some(offset)) => offset,
            (None, None) => return Err(JobError::Invalid("no target given".into())),
        };
        if !offset.iter().all(|v| v.is_finite()) {
            return Err(JobError::Invalid(format!(
                "target {offset:?} px is not finite"
            )));
        }
        let [lo, hi] = stages.travel_px();
        let margin = self.config.overlay.keep_out_um * px_per_um;
        let goal = [now[0] + offset[0], now[1] + offset[1]];
        let inside = (0..2).all(|a| goal[a] >= lo[a] + margin && goal[a] <= hi[a] - margin);
        if !inside {
            return Err(JobError::Invalid(format!(
                "the target lies outside the stages' travel limits (less the {} µm keep-out zone)",
                self.config.overlay.keep_out_um
            )));
        }
        Ok(offset)
    }

    /// Runs an episode; the service has claimed the agent (Running).
    fn start(&mut self, target: Option<Target>, twin_seed: Option<u64>, reply: Reply) {
        self.shared.halt.clear_stop();
        self.take_followed();
        let offset = match self.target_offset(target, twin_seed) {
            Ok(offset) => offset,
            Err(e) => {
                self.shared.job_done();
                let _ = reply.send(Err(e));
                return;
            }
        };
        let episode = {
            let mut status = self.shared.status();
            status.episode += 1;
            status.step = 0;
            status.episode
        };
        let _ = reply.send(Ok(()));
        let header = EpisodeHeader {
            episode,
            policy: self.policy.description.clone(),
            policy_version: self.policy.version,
            target_offset_px: offset,
            rate_hz: self.config.control.rate_hz,
            twin_seed,
        };
        let shared = self.shared.clone();
        let records = self.config.records.dir.clone();
        let version = self.policy.version;
        let started = Instant::now();
        let result = self.instrument.run_recorded(
            &mut self.policy,
            &header,
            &records,
            &shared.halt,
            |log| report_step(&shared, episode, version, log),
        );
        let (ending, steps, time_s) = match result {
            Ok((summary, files)) => {
                tracing::info!(episode, ending = ?summary.ending, steps = summary.steps, record = %files.record.display(), "episode ended");
                self.shared.status().period_ms = summary.timing.period_ms_mean;
                match summary.ending {
                    Ending::Success => shared_count(&self.shared.successes),
                    Ending::Collision => shared_count(&self.shared.collisions),
                    _ => {}
                }
                (Ok(summary.ending), summary.steps, summary.duration_s)
            }
            Err(e) => {
                tracing::error!(%e, "episode failed");
                let steps = self.shared.status().step;
                (Err(e.to_string()), steps, started.elapsed().as_secs_f64())
            }
        };
        // The status first: a client that sees the end on the feed and
        // then asks for the status finds the episode over, and a failed
        // episode ends on the feed too, so that no one waits on it for ever.
        self.shared.episode_done(&ending);
        let _ = self.shared.telemetry.send(Telemetry::End {
            episode,
            policy_version: version,
            steps,
            time_s,
            ending: ending.unwrap_or_else(Ending::Fault),
        });
    }
}

fn shared_count(counter: &std::sync::atomic::AtomicU64) {
    counter.fetch_add(1, Ordering::Relaxed);
}

/// Updates the status and sends telemetry for one step.
fn report_step(shared: &DaemonState, episode: u64, policy_version: u64, log: &StepLog) {
    shared.steps.fetch_add(1, Ordering::Relaxed);
    shared.latency_seconds.observe(log.latency_ms / 1e3);
    {
        let mut status = shared.status();
        status.step = log.step + 1;
        status.stage_mm = log.stage_mm;
        status.detections = log.detected as u32;
        status.latency_ms = log.latency_ms;
        if log.step > 0 {
            status.period_ms = 1000.0 * log.time_s / f64::from(log.step);
        }
    }
    let observation = Observation {
        centres: log.centres.clone(),
        displacements: log.displacements.clone(),
        vector: log.vector,
    };
    let action = Action::clipped(log.action[0], log.action[1]).unwrap_or(Action::ZERO);
    let _ = shared.telemetry.send(Telemetry::Step {
        episode,
        policy_version,
        step: log.step,
        time_s: log.time_s,
        observation,
        action,
        stage_mm: log.stage_mm,
        latency_ms: log.latency_ms,
    });
}
