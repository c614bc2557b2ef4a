//! `tweezer agent ...`.

use crate::AgentCommand;
use crate::connect::{call_error, channel};
use crate::fields;
use crate::watch::Trend;
use anyhow::{Context, anyhow};
use serde::Deserialize;
use std::path::Path;
use tweezer_proto::pb;
use tweezer_proto::pb::hardware_agent_client::HardwareAgentClient;
use tweezer_rpc::AuthChannel;

/// An overlay file, as the hardware agent reads it.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct OverlayFile {
    #[serde(default)]
    discs_um: Vec<[f64; 2]>,
    #[serde(default)]
    walls: Vec<WallEntry>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct WallEntry {
    from_um: [f64; 2],
    to_um: [f64; 2],
}

fn vector([x, y]: [f64; 2]) -> pb::Vector2 {
    pb::Vector2 { x, y }
}

async fn status(client: &mut HardwareAgentClient<AuthChannel>) -> anyhow::Result<pb::AgentStatus> {
    Ok(client
        .get_status(pb::AgentStatusRequest {})
        .await
        .map_err(|e| call_error("GetStatus", e))?
        .into_inner())
}

/// Runs an agent command against the hardware agent at `address`,
/// connecting as the security file `security` says.
pub async fn run(
    security: Option<&Path>,
    address: &str,
    command: AgentCommand,
    json: bool,
) -> anyhow::Result<()> {
    let mut client =
        HardwareAgentClient::new(channel(security, address, "hardware agent", "--agent").await?);
    let reply = match command {
        AgentCommand::Status { watch } => {
            let trends = [Trend::Value("latency_ms"), Trend::Value("loop_period_ms")];
            return crate::watch::repeat(watch, json, &trends, || {
                let mut client = client.clone();
                async move { Ok(fields::agent(&status(&mut client).await?)) }
            })
            .await;
        }
        AgentCommand::Start {
            target_um,
            absolute_mm,
            twin_seed,
            wait,
        } => {
            use pb::start_episode_request::Target;
            let target = match (target_um, absolute_mm) {
                (Some(v), _) => Some(Target::RelativeUm(vector(v))),
                (None, Some([x_mm, y_mm])) => {
                    Some(Target::AbsoluteMm(pb::StagePosition { x_mm, y_mm }))
                }
                (None, None) if twin_seed.is_some() => None,
                (None, None) => {
                    return Err(anyhow!(
                        "give a target: --target-um DX,DY or --absolute-mm X,Y (or, on the twin, --twin-seed N)"
                    ));
                }
            };
            let mut telemetry = if wait {
                Some(
                    client
                        .stream_telemetry(pb::TelemetryRequest {})
                        .await
                        .map_err(|e| call_error("StreamTelemetry", e))?
                        .into_inner(),
                )
            } else {
                None
            };
            let started = client
                .start_episode(pb::StartEpisodeRequest { target, twin_seed })
                .await
                .map_err(|e| call_error("StartEpisode", e))?
                .into_inner();
            if let Some(feed) = telemetry.as_mut() {
                while let Some(message) = feed
                    .message()
                    .await
                    .map_err(|e| call_error("StreamTelemetry", e))?
                {
                    if message.episode == started.episode
                        && message.outcome != pb::Outcome::Running as i32
                    {
                        break;
                    }
                }
                status(&mut client).await?
            } else {
                started
            }
        }
        AgentCommand::Stop => client
            .stop_episode(pb::StopEpisodeRequest {})
            .await
            .map_err(|e| call_error("StopEpisode", e))?
            .into_inner(),
        AgentCommand::Estop { reason } => client
            .emergency_stop(pb::EmergencyStopRequest { reason })
            .await
            .map_err(|e| call_error("EmergencyStop", e))?
            .into_inner(),
        AgentCommand::Reset => client
            .reset_emergency_stop(pb::ResetEmergencyStopRequest {})
            .await
            .map_err(|e| call_error("ResetEmergencyStop", e))?
            .into_inner(),
        AgentCommand::Load {
            file,
            learner,
            greedy,
            planner,
            follow,
        } => {
            use pb::load_policy_request::Source;
            // clap lets at most one source through.
            let source = if let Some(f) = file {
                Source::File(f)
            } else if let Some(s) = learner {
                Source::LearnerSnapshot(s)
            } else if greedy {
                Source::Greedy(true)
            } else if planner {
                Source::Planner(true)
            } else if let Some(tag) = &follow {
                Source::LearnerSnapshot(tag.clone())
            } else {
                return Err(anyhow!(
                    "give the policy: --file SNAPSHOT, --learner best|latest|VERSION, --follow best|latest, --greedy or --planner"
                ));
            };
            client
                .load_policy(pb::LoadPolicyRequest {
                    source: Some(source),
                    follow: follow.is_some(),
                })
                .await
                .map_err(|e| call_error("LoadPolicy", e))?
                .into_inner()
        }
        AgentCommand::Overlay { file } => {
            let text = std::fs::read_to_string(&file)
                .with_context(|| format!("cannot read the overlay file {}", file.display()))?;
            let overlay: OverlayFile = toml::from_str(&text)
                .with_context(|| format!("overlay file {}", file.display()))?;
            let request = pb::SetOverlayRequest {
                discs_um: overlay.discs_um.into_iter().map(vector).collect(),
                walls: overlay
                    .walls
                    .into_iter()
                    .map(|w| pb::Wall {
                        from_um: Some(vector(w.from_um)),
                        to_um: Some(vector(w.to_um)),
                    })
                    .collect(),
            };
            client
                .set_overlay(request)
                .await
                .map_err(|e| call_error("SetOverlay", e))?
                .into_inner()
        }
        AgentCommand::Telemetry { count } => {
            let mut feed = client
                .stream_telemetry(pb::TelemetryRequest {})
                .await
                .map_err(|e| call_error("StreamTelemetry", e))?
                .into_inner();
            let mut seen = 0;
            while count.is_none_or(|c| seen < c) {
                let Some(message) = feed
                    .message()
                    .await
                    .map_err(|e| call_error("StreamTelemetry", e))?
                else {
                    break;
                };
                fields::print(&fields::telemetry(&message), json);
                if !json {
                    println!();
                }
                seen += 1;
            }
            return Ok(());
        }
    };
    fields::print(&fields::agent(&reply), json);
    Ok(())
}
