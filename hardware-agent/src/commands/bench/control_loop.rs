//! The control-loop half of `hardware-agent bench`: a policy on the twin
//! against the same policy on the same seeds in the virtual environment,
//! and the loop's frame-to-command latency.

use serde::Serialize;
use std::path::Path;
use tweezer_gym::{Outcome, evaluate};
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_hardware_agent::control::{Ending, Halt, LoopTiming};
use tweezer_hardware_agent::instrument::Instrument;
use tweezer_hardware_agent::policy_source::LoadedPolicy;
use tweezer_hardware_agent::record::EpisodeHeader;

/// Outcome rates over a set of episodes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Rates {
    /// Reached the target.
    pub success_rate: f64,
    /// Ended in a collision.
    pub collision_rate: f64,
    /// Hit the time limit.
    pub timeout_rate: f64,
    /// Ended otherwise (trap lost, fault): twin only.
    pub other_rate: f64,
}

impl Rates {
    fn of(outcomes: impl IntoIterator<Item = Option<Outcome>>, n: usize) -> Self {
        let mut rates = Self::default();
        let share = 1.0 / n.max(1) as f64;
        for outcome in outcomes {
            match outcome {
                Some(Outcome::Success) => rates.success_rate += share,
                Some(Outcome::Collision) => rates.collision_rate += share,
                Some(Outcome::Timeout) => rates.timeout_rate += share,
                _ => rates.other_rate += share,
            }
        }
        rates
    }
}

/// One policy on the twin and in the virtual environment.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Comparison {
    /// The policy.
    pub policy: String,
    /// Episode seeds run in both.
    pub episodes: usize,
    /// In the virtual environment.
    pub virtual_rates: Rates,
    /// On the twin.
    pub twin_rates: Rates,
    /// Twin success over virtual success (goal ≥ 0.9).
    pub twin_over_virtual: f64,
    /// Share of seeds ending the same way in both.
    pub same_outcome: f64,
    /// Share of twin episodes whose ending the agent judged as the twin's
    /// ground truth has it (collision seen iff one happened; success iff
    /// the trap truly reached the target).
    pub judged_right: f64,
    /// Median frame-to-command latency on the twin, ms.
    pub loop_ms_median: f64,
    /// Its 99th percentile, ms.
    pub loop_ms_p99: f64,
    /// Mean gap between the agent's and the twin's trap position at the
    /// end, px.
    pub position_error_px: f64,
}

/// Runs `make()`'s policy over `seeds` in both environments.
pub fn compare(
    config: &AgentConfig,
    make: &dyn Fn() -> anyhow::Result<LoadedPolicy>,
    seeds: &[u64],
    records: &Path,
) -> anyhow::Result<Comparison> {
    let mut virtual_policy = make()?;
    let stats = evaluate(&config.env, virtual_policy.policy.as_mut(), seeds, 16)?;
    let virtual_outcomes: Vec<Outcome> = stats.iter().map(|s| s.outcome).collect();

    let mut policy = make()?;
    let mut instrument = Instrument::open(config, true)?;
    let halt = Halt::default();
    let (mut twin_outcomes, mut latencies) = (Vec::new(), Vec::new());
    let (mut judged_right, mut position_error) = (0usize, 0.0);
    for (k, &seed) in seeds.iter().enumerate() {
        let target = instrument
            .start_twin_episode(seed)
            .expect("the bench runs on the twin");
        let header = EpisodeHeader {
            episode: k as u64 + 1,
            policy: policy.description.clone(),
            policy_version: policy.version,
            target_offset_px: target,
            rate_hz: config.control.rate_hz,
            twin_seed: Some(seed),
        };
        let (summary, _) =
            instrument.run_recorded(&mut policy, &header, records, &halt, |log| {
                latencies.push(log.latency_ms)
            })?;
        let truth = instrument
            .twin_truth(&summary)
            .expect("the bench runs on the twin");
        let right = match summary.ending {
            Ending::Collision => truth.collided,
            Ending::Success => truth.reached && !truth.collided,
            _ => !truth.collided,
        };
        judged_right += usize::from(right);
        position_error += truth.position_error_px;
        twin_outcomes.push(summary.ending.outcome());
    }
    let n = seeds.len();
    let virtual_rates = Rates::of(virtual_outcomes.iter().map(|&o| Some(o)), n);
    let twin_rates = Rates::of(twin_outcomes.iter().copied(), n);
    let same = virtual_outcomes
        .iter()
        .zip(&twin_outcomes)
        .filter(|(v, t)| Some(**v) == **t)
        .count();
    // Pooled over every episode; LoopTiming's percentiles, its period unused.
    let timing = LoopTiming::of(&mut latencies, 0.0, 0);
    Ok(Comparison {
        policy: policy.description,
        episodes: n,
        twin_over_virtual: twin_rates.success_rate / virtual_rates.success_rate,
        virtual_rates,
        twin_rates,
        same_outcome: same as f64 / n.max(1) as f64,
        judged_right: judged_right as f64 / n.max(1) as f64,
        loop_ms_median: timing.latency_ms_median,
        loop_ms_p99: timing.latency_ms_p99,
        position_error_px: position_error / n.max(1) as f64,
    })
}
