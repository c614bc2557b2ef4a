//! Status messages as named fields, printed as a table or as one JSON
//! object from the same list.

use serde_json::{Map, Value, json};
use tweezer_proto::pb;

/// A status as (name, value) pairs, in display order.
pub type Fields = Vec<(&'static str, Value)>;

/// Prints `fields` as aligned `name  value` lines, or as one JSON line.
pub fn print(fields: &Fields, as_json: bool) {
    if as_json {
        let object: Map<String, Value> = fields
            .iter()
            .map(|(k, v)| ((*k).to_string(), v.clone()))
            .collect();
        println!("{}", Value::Object(object));
        return;
    }
    let width = fields.iter().map(|(k, _)| k.len()).max().unwrap_or(0);
    for (name, value) in fields {
        let shown = match value {
            Value::String(s) => s.clone(),
            Value::Number(n) => match n.as_f64() {
                Some(f) if n.is_f64() => format!("{f:.3}"),
                _ => n.to_string(),
            },
            other => other.to_string(),
        };
        println!("{name:<width$}  {shown}");
    }
}

fn outcome(value: i32) -> String {
    pb::Outcome::try_from(value).map_or_else(
        |_| format!("unknown ({value})"),
        |o| {
            o.as_str_name()
                .trim_start_matches("OUTCOME_")
                .to_lowercase()
        },
    )
}

/// The learner's status.
pub fn learner(s: &pb::LearnerStatus) -> Fields {
    let fill = if s.buffer_capacity > 0 {
        s.buffer_size as f64 / s.buffer_capacity as f64
    } else {
        0.0
    };
    vec![
        ("steps_inserted", json!(s.steps_inserted)),
        ("updates", json!(s.updates)),
        ("buffer_size", json!(s.buffer_size)),
        ("buffer_capacity", json!(s.buffer_capacity)),
        ("buffer_fill", json!(fill)),
        ("insert_rate", json!(s.insert_rate)),
        ("sample_rate", json!(s.sample_rate)),
        ("paused", json!(s.paused)),
        ("limiter_state", json!(s.limiter_state)),
        ("explore_uniformly", json!(s.explore_uniformly)),
        ("connected_actors", json!(s.connected_actors)),
        ("episodes", json!(s.episodes)),
        ("rolling_return", json!(s.rolling_return)),
        ("success_rate", json!(s.success_rate)),
        ("latest_snapshot", json!(s.latest_snapshot)),
        ("best_snapshot", json!(s.best_snapshot)),
        ("critic_loss", json!(s.critic_loss)),
        ("actor_loss", json!(s.actor_loss)),
        ("mean_q", json!(s.mean_q)),
        ("malformed_batches", json!(s.malformed_batches)),
        ("duplicate_batches", json!(s.duplicate_batches)),
        ("diverged_updates", json!(s.diverged_updates)),
        ("known_actors", json!(s.known_actors)),
    ]
}

/// An actor's row, as the learner sees it.
pub fn actor(a: &pb::ActorStatus) -> Fields {
    vec![
        ("id", json!(a.id)),
        ("session", json!(a.session)),
        ("token", json!(a.token)),
        ("streams", json!(a.streams)),
        ("steps", json!(a.steps)),
        ("episodes", json!(a.episodes)),
        ("idle_seconds", json!(a.idle_seconds)),
        ("last_sequence", json!(a.last_sequence)),
    ]
}

/// A snapshot's metadata.
pub fn snapshot(info: &pb::SnapshotInfo) -> Fields {
    vec![
        ("version", json!(info.version)),
        ("training_step", json!(info.training_step)),
        ("size_bytes", json!(info.size_bytes)),
        ("sha256", json!(info.sha256)),
        ("architecture", json!(info.architecture)),
        ("image", json!([info.image_width, info.image_height])),
        ("network", json!(info.network)),
    ]
}

/// The hardware agent's status.
pub fn agent(s: &pb::AgentStatus) -> Fields {
    let state = pb::AgentState::try_from(s.state).map_or_else(
        |_| format!("unknown ({})", s.state),
        |st| {
            st.as_str_name()
                .trim_start_matches("AGENT_STATE_")
                .to_lowercase()
        },
    );
    let stage = s.stage.unwrap_or_default();
    vec![
        ("state", json!(state)),
        ("episode", json!(s.episode)),
        ("step", json!(s.step)),
        ("stage_x_mm", json!(stage.x_mm)),
        ("stage_y_mm", json!(stage.y_mm)),
        ("last_outcome", json!(outcome(s.last_outcome))),
        ("policy", json!(s.policy)),
        ("policy_version", json!(s.policy_version)),
        ("following", json!(s.following)),
        ("loop_period_ms", json!(s.loop_period_ms)),
        ("latency_ms", json!(s.latency_ms)),
        ("detections", json!(s.detections)),
        ("virtual_obstacles", json!(s.virtual_obstacles)),
        ("message", json!(s.message)),
    ]
}

/// One telemetry message.
pub fn telemetry(t: &pb::Telemetry) -> Fields {
    let action = t.action.unwrap_or_default();
    let stage = t.stage.unwrap_or_default();
    let observation = t.observation.clone().unwrap_or_default();
    vec![
        ("episode", json!(t.episode)),
        ("policy_version", json!(t.policy_version)),
        ("step", json!(t.step)),
        ("time_s", json!(t.time_s)),
        ("outcome", json!(outcome(t.outcome))),
        ("action", json!([action.x, action.y])),
        (
            "vector",
            json!([observation.vector_x, observation.vector_y]),
        ),
        ("spheres", json!(observation.centres.len() / 2)),
        ("stage_mm", json!([stage.x_mm, stage.y_mm])),
        ("latency_ms", json!(t.latency_ms)),
    ]
}
