//! Wire ↔ domain conversions. Decoding validates and names the offending
//! field, e.g. `steps[3].observation.centres: odd length 7`.

use crate::pb;
use tweezer_gym::{
    Action, EpisodeEnd, Observation, ObservationBounds, Outcome, StepBounds, StepRecord,
};

/// A malformed message: which field, and what is wrong with it.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("invalid {field}: {reason}")]
pub struct WireError {
    /// Path of the field in the message, e.g. `steps[2].action`.
    pub field: String,
    /// What is wrong.
    pub reason: String,
}

impl WireError {
    fn new(field: &str, reason: impl ToString) -> Self {
        Self {
            field: field.to_string(),
            reason: reason.to_string(),
        }
    }
}

impl From<WireError> for tonic::Status {
    fn from(e: WireError) -> Self {
        tonic::Status::invalid_argument(e.to_string())
    }
}

/// Decodes and validates an observation; `field` names it in errors.
pub fn observation_from_wire(
    msg: &pb::Observation,
    bounds: &ObservationBounds,
    field: &str,
) -> Result<Observation, WireError> {
    if !msg.centres.len().is_multiple_of(2) {
        return Err(WireError::new(
            &format!("{field}.centres"),
            format!("odd length {}: centres are (x, y) pairs", msg.centres.len()),
        ));
    }
    if !msg.displacements.is_empty() && msg.displacements.len() != msg.centres.len() {
        return Err(WireError::new(
            &format!("{field}.displacements"),
            format!(
                "{} values for {} centre coordinates: give none, or one (dx, dy) pair per centre",
                msg.displacements.len(),
                msg.centres.len()
            ),
        ));
    }
    let observation = Observation {
        centres: msg.centres.chunks_exact(2).map(|c| [c[0], c[1]]).collect(),
        displacements: msg
            .displacements
            .chunks_exact(2)
            .map(|d| (!(d[0].is_nan() && d[1].is_nan())).then_some([d[0], d[1]]))
            .collect(),
        vector: [msg.vector_x, msg.vector_y],
    };
    observation
        .validate(bounds)
        .map_err(|e| WireError::new(field, e))?;
    Ok(observation)
}

/// Encodes an observation.
pub fn observation_to_wire(observation: &Observation) -> pb::Observation {
    pb::Observation {
        centres: observation.centres.iter().flatten().copied().collect(),
        displacements: observation
            .displacements
            .iter()
            .flat_map(|d| d.unwrap_or([f32::NAN; 2]))
            .collect(),
        vector_x: observation.vector[0],
        vector_y: observation.vector[1],
    }
}

/// Decodes and validates an action (each component finite and in [-1, 1]).
pub fn action_from_wire(msg: Option<&pb::Action>, field: &str) -> Result<Action, WireError> {
    let msg = msg.ok_or_else(|| WireError::new(field, "missing"))?;
    Action::new(msg.x, msg.y).map_err(|e| WireError::new(field, e))
}

/// Encodes an action.
pub fn action_to_wire(action: Action) -> pb::Action {
    let [x, y] = action.components();
    pb::Action { x, y }
}

/// Encodes an episode outcome.
pub fn outcome_to_wire(outcome: Outcome) -> pb::Outcome {
    match outcome {
        Outcome::Running => pb::Outcome::Running,
        Outcome::Success => pb::Outcome::Success,
        Outcome::Collision => pb::Outcome::Collision,
        Outcome::Timeout => pb::Outcome::Timeout,
    }
}

/// The outcome a step's end flags allow: `None` while the episode runs.
fn end_outcome(wire: i32, terminated: bool, truncated: bool) -> Result<Option<Outcome>, String> {
    let outcome = pb::Outcome::try_from(wire).map_err(|_| format!("unknown outcome {wire}"))?;
    match (outcome, terminated, truncated) {
        (pb::Outcome::Unspecified | pb::Outcome::Running, false, false) => Ok(None),
        (pb::Outcome::Success, true, _) => Ok(Some(Outcome::Success)),
        (pb::Outcome::Collision, true, _) => Ok(Some(Outcome::Collision)),
        (pb::Outcome::Timeout, _, true) => Ok(Some(Outcome::Timeout)),
        (outcome, terminated, truncated) => Err(format!(
            "{} does not match terminated={terminated}, truncated={truncated}",
            outcome.as_str_name()
        )),
    }
}

/// Decodes and validates one step; `field` names it in errors.
pub fn step_from_wire(
    msg: &pb::Step,
    bounds: &StepBounds,
    field: &str,
) -> Result<StepRecord, WireError> {
    let observation = msg
        .observation
        .as_ref()
        .ok_or_else(|| WireError::new(&format!("{field}.observation"), "missing"))?;
    let observation = observation_from_wire(
        observation,
        &bounds.observation,
        &format!("{field}.observation"),
    )?;
    let action = action_from_wire(msg.action.as_ref(), &format!("{field}.action"))?;
    bounds
        .check_reward(msg.reward)
        .map_err(|reason| WireError::new(&format!("{field}.reward"), reason))?;
    let kind = match (msg.terminated, msg.truncated) {
        (true, true) => {
            return Err(WireError::new(
                &format!("{field}.truncated"),
                "a step cannot be both terminated and truncated",
            ));
        }
        (terminated, truncated) => end_outcome(msg.outcome, terminated, truncated)
            .map_err(|reason| WireError::new(&format!("{field}.outcome"), reason))?,
    };
    let final_field = format!("{field}.final_observation");
    let end = match (kind, msg.final_observation.as_ref()) {
        (None, None) => None,
        (None, Some(_)) => {
            return Err(WireError::new(
                &final_field,
                "set on a step that did not end its episode",
            ));
        }
        (Some(_), None) => {
            return Err(WireError::new(
                &final_field,
                "missing on a step that ended its episode",
            ));
        }
        (Some(outcome), Some(last)) => Some(EpisodeEnd {
            outcome,
            final_observation: observation_from_wire(last, &bounds.observation, &final_field)?,
        }),
    };
    Ok(StepRecord {
        env: msg.env,
        episode: msg.episode,
        t: msg.t,
        observation,
        action,
        reward: msg.reward,
        end,
    })
}

/// Encodes one step.
pub fn step_to_wire(step: &StepRecord) -> pb::Step {
    pb::Step {
        env: step.env,
        episode: step.episode,
        t: step.t,
        observation: Some(observation_to_wire(&step.observation)),
        action: Some(action_to_wire(step.action)),
        reward: step.reward,
        terminated: step.terminated(),
        truncated: step.truncated(),
        final_observation: step
            .end
            .as_ref()
            .map(|e| observation_to_wire(&e.final_observation)),
        outcome: step
            .end
            .as_ref()
            .map_or(pb::Outcome::Running, |e| outcome_to_wire(e.outcome))
            .into(),
    }
}

/// Most steps one batch may carry.
pub const MAX_BATCH_STEPS: usize = 4096;

/// Longest actor id.
pub const MAX_ACTOR_ID: usize = 128;

/// Actor ids are 1 to 128 characters of letters, digits and `.`, `_`, `-`,
/// `:` (host names, pod names, Slurm task ids).
pub fn check_actor_id(id: &str) -> Result<(), WireError> {
    if id.is_empty() {
        return Err(WireError::new("actor_id", "empty"));
    }
    let ok = id.len() <= MAX_ACTOR_ID
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"._-:".contains(&b));
    if ok {
        Ok(())
    } else {
        Err(WireError::new(
            "actor_id",
            format!(
                "`{}` is not a valid actor id (1-{MAX_ACTOR_ID} letters, digits, `.`, `_`, `-`, `:`)",
                id.chars().take(MAX_ACTOR_ID).collect::<String>()
            ),
        ))
    }
}

/// Decodes and validates a batch: a non-empty actor id, at most `max_steps`
/// steps, each step valid. Returns the actor id, the sequence number and the
/// steps.
pub fn step_batch_from_wire(
    msg: &pb::StepBatch,
    bounds: &StepBounds,
    max_steps: usize,
) -> Result<(String, u64, Vec<StepRecord>), WireError> {
    check_actor_id(&msg.actor_id)?;
    if msg.steps.len() > max_steps {
        return Err(WireError::new(
            "steps",
            format!(
                "{} steps, more than the {max_steps} a batch may hold",
                msg.steps.len()
            ),
        ));
    }
    let steps = msg
        .steps
        .iter()
        .enumerate()
        .map(|(i, s)| step_from_wire(s, bounds, &format!("steps[{i}]")))
        .collect::<Result<_, _>>()?;
    Ok((msg.actor_id.clone(), msg.sequence, steps))
}

#[cfg(test)]
mod tests {
    use super::*;
    use prost::Message;
    use tweezer_gym::EnvConfig;

    fn bounds() -> StepBounds {
        StepBounds::for_config(&EnvConfig::default())
    }

    fn observation() -> Observation {
        Observation {
            centres: vec![[10.0, 20.0], [-5.5, 1030.25]],
            displacements: vec![None, Some([1.5, -2.25])],
            vector: [0.6, -0.8],
        }
    }

    fn step(end: Option<EpisodeEnd>) -> StepRecord {
        StepRecord {
            env: 3,
            episode: 77,
            t: 12,
            observation: observation(),
            action: Action::new(0.5, -1.0).unwrap(),
            reward: 9.5,
            end,
        }
    }

    fn ended(outcome: Outcome) -> Option<EpisodeEnd> {
        Some(EpisodeEnd {
            outcome,
            final_observation: Observation {
                vector: [0.0, 0.01],
                ..Observation::default()
            },
        })
    }

    #[test]
    fn steps_round_trip_through_bytes() {
        for s in [
            step(None),
            step(ended(Outcome::Success)),
            step(ended(Outcome::Collision)),
            step(ended(Outcome::Timeout)),
        ] {
            let bytes = step_to_wire(&s).encode_to_vec();
            let decoded = pb::Step::decode(bytes.as_slice()).unwrap();
            assert_eq!(step_from_wire(&decoded, &bounds(), "step").unwrap(), s);
        }
    }

    fn field_of(msg: &pb::Step) -> String {
        step_from_wire(msg, &bounds(), "steps[4]")
            .unwrap_err()
            .field
    }

    #[test]
    fn malformed_steps_name_the_field() {
        let good = step_to_wire(&step(None));

        let mut m = good.clone();
        m.observation.as_mut().unwrap().centres.push(1.0);
        assert_eq!(field_of(&m), "steps[4].observation.centres");

        let mut m = good.clone();
        m.observation.as_mut().unwrap().centres[1] = f32::NAN;
        assert_eq!(field_of(&m), "steps[4].observation");

        let mut m = good.clone();
        m.observation.as_mut().unwrap().vector_x = 2.0;
        assert_eq!(field_of(&m), "steps[4].observation");

        let mut m = good.clone();
        m.observation.as_mut().unwrap().centres[0] = 5000.0;
        assert_eq!(field_of(&m), "steps[4].observation");

        let mut m = good.clone();
        m.observation.as_mut().unwrap().displacements.pop();
        assert_eq!(field_of(&m), "steps[4].observation.displacements");

        // One coordinate of a pair NaN is no new sphere, but a bad move.
        let mut m = good.clone();
        m.observation.as_mut().unwrap().displacements[2] = f32::NAN;
        assert_eq!(field_of(&m), "steps[4].observation");

        let mut m = good.clone();
        m.observation = None;
        assert_eq!(field_of(&m), "steps[4].observation");

        let mut m = good.clone();
        m.action.as_mut().unwrap().x = 1.5;
        assert_eq!(field_of(&m), "steps[4].action");

        let mut m = good.clone();
        m.action.as_mut().unwrap().y = f32::INFINITY;
        assert_eq!(field_of(&m), "steps[4].action");

        let mut m = good.clone();
        m.action = None;
        assert_eq!(field_of(&m), "steps[4].action");

        let mut m = good.clone();
        m.reward = f32::NAN;
        assert_eq!(field_of(&m), "steps[4].reward");

        // Finite, but more than any step of this environment can earn.
        let mut m = good.clone();
        m.reward = 1e30;
        assert_eq!(field_of(&m), "steps[4].reward");

        let mut m = good.clone();
        m.terminated = true;
        m.truncated = true;
        assert_eq!(field_of(&m), "steps[4].truncated");

        let mut m = good.clone();
        m.terminated = true;
        assert_eq!(field_of(&m), "steps[4].outcome");

        let mut m = good.clone();
        m.terminated = true;
        m.outcome = pb::Outcome::Timeout.into();
        assert_eq!(field_of(&m), "steps[4].outcome");

        let mut m = good.clone();
        m.outcome = 99;
        assert_eq!(field_of(&m), "steps[4].outcome");

        let mut m = good.clone();
        m.terminated = true;
        m.outcome = pb::Outcome::Success.into();
        assert_eq!(field_of(&m), "steps[4].final_observation");

        let mut m = good;
        m.final_observation = Some(observation_to_wire(&observation()));
        assert_eq!(field_of(&m), "steps[4].final_observation");
    }

    #[test]
    fn errors_read_well_and_become_invalid_argument() {
        let mut m = step_to_wire(&step(None));
        m.observation.as_mut().unwrap().centres.push(1.0);
        let err = step_from_wire(&m, &bounds(), "steps[0]").unwrap_err();
        assert_eq!(
            err.to_string(),
            "invalid steps[0].observation.centres: odd length 5: centres are (x, y) pairs"
        );
        let status = tonic::Status::from(err);
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
        assert!(status.message().contains("odd length"));
    }

    #[test]
    fn batches_are_checked_whole() {
        let batch = pb::StepBatch {
            actor_id: "actor-1".into(),
            session: 3,
            sequence: 9,
            steps: vec![step_to_wire(&step(None)); 3],
        };
        let (actor, sequence, steps) = step_batch_from_wire(&batch, &bounds(), 3).unwrap();
        assert_eq!((actor.as_str(), sequence, steps.len()), ("actor-1", 9, 3));
        assert_eq!(
            step_batch_from_wire(&batch, &bounds(), 2)
                .unwrap_err()
                .field,
            "steps"
        );

        let mut bad = batch.clone();
        bad.steps[2].reward = f32::INFINITY;
        assert_eq!(
            step_batch_from_wire(&bad, &bounds(), 3).unwrap_err().field,
            "steps[2].reward"
        );

        let mut anonymous = batch;
        anonymous.actor_id = " ".into();
        assert_eq!(
            step_batch_from_wire(&anonymous, &bounds(), 3)
                .unwrap_err()
                .field,
            "actor_id"
        );
    }

    #[test]
    fn actions_and_outcomes_encode() {
        let a = Action::new(-0.25, 1.0).unwrap();
        assert_eq!(action_from_wire(Some(&action_to_wire(a)), "a").unwrap(), a);
        assert_eq!(outcome_to_wire(Outcome::Collision), pb::Outcome::Collision);
    }
}
