//! `actor act`: a policy's actions for observations given as JSON lines,
//! the reference that other implementations of a policy (the Python
//! package) are checked against.

use anyhow::{Context, bail};
use serde::{Deserialize, Serialize};
use std::io::{BufRead, Write};
use tweezer_gym::{Action, EnvConfig, Observation, ObservationBounds, Policy};

/// One observation as a line of input.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ObservationLine {
    /// Free spheres' centres, FOV px.
    centres: Vec<[f32; 2]>,
    /// Each centre's move since the previous step, px, `null` for one new
    /// to the view; absent: none known.
    #[serde(default)]
    displacements: Vec<Option<[f32; 2]>>,
    /// The target vector.
    vector: [f32; 2],
}

/// One action as a line of output.
#[derive(Serialize)]
struct ActionLine {
    action: [f32; 2],
}

/// Reads observations (`{"centres": [[x, y], ...], "vector": [x, y]}`, one
/// per line) from `input`, checks each against `env`'s bounds, and writes
/// `policy`'s action for each (`{"action": [x, y]}`) to `output`, acting
/// on `batch` observations at a time.
pub fn run(
    env: &EnvConfig,
    policy: &mut dyn Policy,
    input: impl BufRead,
    mut output: impl Write,
    batch: usize,
) -> anyhow::Result<usize> {
    if batch == 0 {
        bail!("--batch must be at least 1");
    }
    let bounds = ObservationBounds::for_config(env);
    let mut pending = Vec::with_capacity(batch);
    let mut done = 0;
    let mut flush = |pending: &mut Vec<Observation>, output: &mut dyn Write| {
        let refs: Vec<&Observation> = pending.iter().collect();
        let mut actions = vec![Action::ZERO; refs.len()];
        policy.act(&refs, &mut actions);
        for a in &actions {
            let line = ActionLine {
                action: a.components(),
            };
            writeln!(output, "{}", serde_json::to_string(&line)?)?;
        }
        pending.clear();
        anyhow::Ok(actions.len())
    };
    for (k, line) in input.lines().enumerate() {
        let line = line.with_context(|| format!("cannot read observation line {}", k + 1))?;
        if line.trim().is_empty() {
            continue;
        }
        let parsed: ObservationLine =
            serde_json::from_str(&line).with_context(|| format!("observation line {}", k + 1))?;
        let observation = Observation {
            centres: parsed.centres,
            displacements: parsed.displacements,
            vector: parsed.vector,
        };
        observation
            .validate(&bounds)
            .with_context(|| format!("observation line {}", k + 1))?;
        pending.push(observation);
        if pending.len() == batch {
            done += flush(&mut pending, &mut output)?;
        }
    }
    if !pending.is_empty() {
        done += flush(&mut pending, &mut output)?;
    }
    output.flush()?;
    Ok(done)
}
