//! The `tweezer.v1.HardwareAgent` gRPC service: wire types in, jobs and
//! halt requests out, the shared status back as wire types.

use super::control_thread::{Job, JobError, Target};
use super::state::{Activity, DaemonState, State, Status, Telemetry};
use std::pin::Pin;
use std::sync::Arc;
use std::sync::mpsc::Sender;
use std::time::{Duration, Instant};
use tokio::sync::{broadcast, mpsc, oneshot};
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status as RpcStatus};
use tweezer_gym::Baseline;
use tweezer_hardware_agent::control::{Ending, HaltKind};
use tweezer_hardware_agent::overlay::{MAX_DISCS, OverlaySpec, Wall};
use tweezer_hardware_agent::policy_source::{PolicyChoice, SnapshotChoice};
use tweezer_proto::pb::hardware_agent_server::HardwareAgent;
use tweezer_proto::{action_to_wire, observation_to_wire, pb};

/// How long StopEpisode waits for the loop to end before answering.
const STOP_WAIT: Duration = Duration::from_secs(3);
/// Longest an emergency stop's reason may be.
const MAX_REASON: usize = 1000;

type TelemetryStream = Pin<Box<dyn Stream<Item = Result<pb::Telemetry, RpcStatus>> + Send>>;

/// The service over the shared state.
pub struct AgentService {
    shared: Arc<DaemonState>,
    jobs: Sender<Job>,
}

impl AgentService {
    pub fn new(shared: Arc<DaemonState>, jobs: Sender<Job>) -> Self {
        Self { shared, jobs }
    }

    fn status(&self) -> Response<pb::AgentStatus> {
        Response::new(status_to_wire(&self.shared.status()))
    }

    /// Claims the idle agent as `state`, hands the control thread a job
    /// and waits for its answer.
    async fn submit(
        &self,
        activity: Activity,
        job: impl FnOnce(oneshot::Sender<Result<(), JobError>>) -> Job,
    ) -> Result<(), RpcStatus> {
        self.shared
            .claim(activity)
            .map_err(RpcStatus::failed_precondition)?;
        let (reply, answer) = oneshot::channel();
        self.jobs
            .send(job(reply))
            .map_err(|_| RpcStatus::unavailable("the control thread has stopped"))?;
        match answer.await {
            Ok(Ok(())) => Ok(()),
            Ok(Err(JobError::Refused(why))) => Err(RpcStatus::failed_precondition(why)),
            Ok(Err(JobError::Invalid(why))) => Err(RpcStatus::invalid_argument(why)),
            Ok(Err(JobError::Unreachable(why))) => Err(RpcStatus::unavailable(why)),
            Err(_) => Err(RpcStatus::unavailable("the control thread has stopped")),
        }
    }
}

fn finite(v: &pb::Vector2, field: &str) -> Result<[f64; 2], RpcStatus> {
    if v.x.is_finite() && v.y.is_finite() {
        Ok([v.x, v.y])
    } else {
        Err(RpcStatus::invalid_argument(format!(
            "{field} = ({}, {}) must be finite",
            v.x, v.y
        )))
    }
}

#[tonic::async_trait]
impl HardwareAgent for AgentService {
    type StreamTelemetryStream = TelemetryStream;

    async fn get_status(
        &self,
        _: Request<pb::AgentStatusRequest>,
    ) -> Result<Response<pb::AgentStatus>, RpcStatus> {
        Ok(self.status())
    }

    async fn start_episode(
        &self,
        request: Request<pb::StartEpisodeRequest>,
    ) -> Result<Response<pb::AgentStatus>, RpcStatus> {
        let request = request.into_inner();
        let target = match &request.target {
            Some(pb::start_episode_request::Target::RelativeUm(v)) => {
                Some(Target::RelativeUm(finite(v, "relative_um")?))
            }
            Some(pb::start_episode_request::Target::AbsoluteMm(p)) => {
                let mm = [p.x_mm, p.y_mm];
                if !mm.iter().all(|v| v.is_finite()) {
                    return Err(RpcStatus::invalid_argument(format!(
                        "absolute_mm = {mm:?} must be finite"
                    )));
                }
                Some(Target::AbsoluteMm(mm))
            }
            None => None,
        };
        let twin_seed = request.twin_seed;
        self.submit(Activity::Running, |reply| Job::Start {
            target,
            twin_seed,
            reply,
        })
        .await?;
        Ok(self.status())
    }

    async fn stop_episode(
        &self,
        _: Request<pb::StopEpisodeRequest>,
    ) -> Result<Response<pb::AgentStatus>, RpcStatus> {
        if self.shared.status().activity == Activity::Running {
            self.shared.halt.request(HaltKind::Stop);
            let deadline = Instant::now() + STOP_WAIT;
            while self.shared.status().activity == Activity::Running && Instant::now() < deadline {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        }
        Ok(self.status())
    }

    async fn emergency_stop(
        &self,
        request: Request<pb::EmergencyStopRequest>,
    ) -> Result<Response<pb::AgentStatus>, RpcStatus> {
        let mut reason: String = request.into_inner().reason;
        reason.truncate(reason.floor_char_boundary(MAX_REASON));
        if reason.is_empty() {
            reason = "emergency stop".into();
        }
        // The loop may be anywhere: it checks for the request after every
        // command, so no command of its can follow this stop unseen.
        let sent = self.shared.emergency_stop(reason.clone());
        tracing::warn!(%reason, sent = sent.is_ok(), "emergency stop");
        Ok(self.status())
    }

    async fn reset_emergency_stop(
        &self,
        _: Request<pb::ResetEmergencyStopRequest>,
    ) -> Result<Response<pb::AgentStatus>, RpcStatus> {
        self.shared
            .reset()
            .map_err(RpcStatus::failed_precondition)?;
        Ok(self.status())
    }

    async fn load_policy(
        &self,
        request: Request<pb::LoadPolicyRequest>,
    ) -> Result<Response<pb::AgentStatus>, RpcStatus> {
        use pb::load_policy_request::Source;
        let request = request.into_inner();
        let choice = match request.source {
            Some(Source::LearnerSnapshot(s)) if request.follow => {
                match SnapshotChoice::parse(&s).map_err(RpcStatus::invalid_argument)? {
                    SnapshotChoice::Version(v) => {
                        return Err(RpcStatus::invalid_argument(format!(
                            "follow: only \"best\" or \"latest\" can be followed, not version {v}"
                        )));
                    }
                    tag => PolicyChoice::Follow(tag),
                }
            }
            Some(Source::LearnerSnapshot(s)) => PolicyChoice::Learner(
                SnapshotChoice::parse(&s).map_err(RpcStatus::invalid_argument)?,
            ),
            Some(_) if request.follow => {
                return Err(RpcStatus::invalid_argument(
                    "follow applies to learner_snapshot \"best\" or \"latest\" only",
                ));
            }
            Some(Source::File(f)) if !f.is_empty() => PolicyChoice::File(f.into()),
            Some(Source::Greedy(true)) => PolicyChoice::Baseline(Baseline::Greedy),
            Some(Source::Planner(true)) => PolicyChoice::Baseline(Baseline::Planner),
            _ => {
                return Err(RpcStatus::invalid_argument(
                    "source: give learner_snapshot, file, greedy = true or planner = true",
                ));
            }
        };
        self.submit(Activity::Loading, |reply| Job::LoadPolicy { choice, reply })
            .await?;
        Ok(self.status())
    }

    async fn set_overlay(
        &self,
        request: Request<pb::SetOverlayRequest>,
    ) -> Result<Response<pb::AgentStatus>, RpcStatus> {
        let request = request.into_inner();
        if request.discs_um.len() + request.walls.len() > MAX_DISCS {
            return Err(RpcStatus::invalid_argument(format!(
                "the overlay lists more than {MAX_DISCS} items"
            )));
        }
        let mut spec = OverlaySpec::default();
        for (k, d) in request.discs_um.iter().enumerate() {
            spec.discs_um.push(finite(d, &format!("discs_um[{k}]"))?);
        }
        for (k, w) in request.walls.iter().enumerate() {
            let end = |v: &Option<pb::Vector2>, name: &str| {
                let field = format!("walls[{k}].{name}");
                v.as_ref()
                    .ok_or_else(|| RpcStatus::invalid_argument(format!("{field} is missing")))
                    .and_then(|v| finite(v, &field))
            };
            spec.walls.push(Wall {
                from_um: end(&w.from_um, "from_um")?,
                to_um: end(&w.to_um, "to_um")?,
            });
        }
        self.submit(Activity::Loading, |reply| Job::SetOverlay { spec, reply })
            .await?;
        Ok(self.status())
    }

    async fn stream_telemetry(
        &self,
        _: Request<pb::TelemetryRequest>,
    ) -> Result<Response<Self::StreamTelemetryStream>, RpcStatus> {
        let mut feed = self.shared.telemetry.subscribe();
        let (tx, rx) = mpsc::channel(64);
        tokio::spawn(async move {
            loop {
                match feed.recv().await {
                    Ok(message) => {
                        if tx.send(Ok(telemetry_to_wire(message))).await.is_err() {
                            break;
                        }
                    }
                    Err(broadcast::error::RecvError::Lagged(skipped)) => {
                        tracing::debug!(skipped, "a telemetry subscriber fell behind");
                    }
                    Err(broadcast::error::RecvError::Closed) => break,
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
}

/// A telemetry message on the wire.
fn telemetry_to_wire(telemetry: Telemetry) -> pb::Telemetry {
    match telemetry {
        Telemetry::Step {
            episode,
            policy_version,
            step,
            time_s,
            observation,
            action,
            stage_mm,
            latency_ms,
        } => pb::Telemetry {
            episode,
            step,
            time_s,
            observation: Some(observation_to_wire(&observation)),
            action: Some(action_to_wire(action)),
            stage: Some(pb::StagePosition {
                x_mm: stage_mm[0],
                y_mm: stage_mm[1],
            }),
            latency_ms,
            outcome: pb::Outcome::Running.into(),
            policy_version,
        },
        Telemetry::End {
            episode,
            policy_version,
            steps,
            time_s,
            ending,
        } => pb::Telemetry {
            episode,
            step: steps,
            time_s,
            outcome: ending_to_wire(&ending).into(),
            policy_version,
            ..pb::Telemetry::default()
        },
    }
}

/// The wire outcome of an ending.
fn ending_to_wire(ending: &Ending) -> pb::Outcome {
    match ending {
        Ending::Success => pb::Outcome::Success,
        Ending::Collision => pb::Outcome::Collision,
        Ending::Timeout => pb::Outcome::Timeout,
        Ending::Stopped | Ending::EmergencyStopped(_) => pb::Outcome::Stopped,
        Ending::TrapLost | Ending::Fault(_) => pb::Outcome::Fault,
    }
}

/// The status on the wire.
fn status_to_wire(status: &Status) -> pb::AgentStatus {
    let state = match status.state() {
        State::Idle => pb::AgentState::Idle,
        State::Running => pb::AgentState::Running,
        State::EmergencyStopped => pb::AgentState::EmergencyStopped,
        State::Fault => pb::AgentState::Fault,
        State::Loading => pb::AgentState::Loading,
    };
    pb::AgentStatus {
        state: state.into(),
        episode: status.episode,
        step: status.step,
        stage: Some(pb::StagePosition {
            x_mm: status.stage_mm[0],
            y_mm: status.stage_mm[1],
        }),
        last_outcome: status
            .last_ending
            .as_ref()
            .map_or(pb::Outcome::Unspecified, ending_to_wire)
            .into(),
        policy_version: status.policy_version,
        loop_period_ms: status.period_ms,
        message: status.message().to_string(),
        policy: status.policy.clone(),
        detections: status.detections,
        latency_ms: status.latency_ms,
        virtual_obstacles: status.virtual_obstacles as u32,
        following: status.following.clone(),
    }
}
