//! One environment step as an actor reports it to the learner.

use crate::action::Action;
use crate::config::EnvConfig;
use crate::env::Outcome;
use crate::observation::{Observation, ObservationBounds};

/// One step of one environment. The transition of step `t` is
/// (observation, action, reward, next observation), where the next
/// observation is that of step `t + 1` of the same environment and episode,
/// or the final observation carried by `end`.
#[derive(Clone, Debug, PartialEq)]
pub struct StepRecord {
    /// Index of the environment within its actor.
    pub env: u32,
    /// The episode's seed.
    pub episode: u64,
    /// Step index within the episode, from 0.
    pub t: u32,
    /// The observation the action responded to.
    pub observation: Observation,
    /// The action taken.
    pub action: Action,
    /// The step's reward.
    pub reward: f32,
    /// Set when this step ended the episode.
    pub end: Option<EpisodeEnd>,
}

/// How a step ended its episode.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeEnd {
    /// Success or collision (terminated), or timeout (truncated).
    pub outcome: Outcome,
    /// The observation after the step.
    pub final_observation: Observation,
}

impl StepRecord {
    /// The step ended the episode in success or collision.
    pub fn terminated(&self) -> bool {
        matches!(&self.end, Some(e) if matches!(e.outcome, Outcome::Success | Outcome::Collision))
    }

    /// The step hit the time limit.
    pub fn truncated(&self) -> bool {
        matches!(&self.end, Some(e) if e.outcome == Outcome::Timeout)
    }
}

/// What a step from an environment with a given configuration can hold:
/// anything outside came from elsewhere.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepBounds {
    /// The observations' bounds.
    pub observation: ObservationBounds,
    /// The smallest and largest reward, widened by f32 rounding.
    pub reward: [f32; 2],
}

impl StepBounds {
    /// The bounds of steps an environment with `config` produces.
    pub fn for_config(config: &EnvConfig) -> Self {
        // Rewards are summed in f64 and sent as f32: allow for both.
        let slack = |r: f64| 1e-5 * r.abs() + 1e-6;
        let [lo, hi] = config.reward_range();
        Self {
            observation: ObservationBounds::for_config(config),
            reward: [(lo - slack(lo)) as f32, (hi + slack(hi)) as f32],
        }
    }

    /// Checks a reward against the range; the error says what is allowed.
    pub fn check_reward(&self, reward: f32) -> Result<(), String> {
        let [lo, hi] = self.reward;
        if (lo..=hi).contains(&reward) {
            Ok(())
        } else {
            Err(format!(
                "{reward} is outside [{lo}, {hi}], the rewards this environment can give"
            ))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{RewardComponent, SplitMix64, VecEnv};

    #[test]
    fn every_reward_of_random_episodes_lies_within_the_bounds() {
        let dense = EnvConfig {
            min_free_spheres: 1000,
            max_free_spheres: 1000,
            ..EnvConfig::default()
        };
        let mut no_carry = EnvConfig::default();
        no_carry.rewards.off = vec![RewardComponent::Carry, RewardComponent::Time];
        let mut ends = 0;
        for config in [EnvConfig::default(), dense, no_carry] {
            let bounds = StepBounds::for_config(&config);
            let mut envs = VecEnv::new(&config, 8, 3).unwrap();
            let mut rng = SplitMix64::new(1);
            for _ in 0..3000 {
                // Full-speed moves, where the carry reward is largest.
                let actions: Vec<Action> = (0..envs.len())
                    .map(|_| {
                        let corner = |r: f64| if r < 0.5 { -1.0 } else { 1.0 };
                        Action::new(corner(rng.unit()), corner(rng.unit())).unwrap()
                    })
                    .collect();
                envs.step(&actions).unwrap();
                for (i, slot) in envs.slots().iter().enumerate() {
                    let record = slot.record(i as u32).unwrap();
                    ends += usize::from(record.end.is_some());
                    bounds.check_reward(record.reward).unwrap();
                }
            }
        }
        assert!(ends > 0, "no episode ended: the end rewards went untested");
    }

    #[test]
    fn a_reward_no_environment_gives_is_refused_naming_the_range() {
        let bounds = StepBounds::for_config(&EnvConfig::default());
        let [lo, hi] = EnvConfig::default().reward_range();
        assert!(lo < -1.0 && hi > 1.0, "[{lo}, {hi}]");
        let err = bounds.check_reward(1e30).unwrap_err();
        assert!(err.contains("outside"), "{err}");
        assert!(bounds.check_reward((hi * 1.01) as f32).is_err());
        assert!(bounds.check_reward(lo as f32).is_ok());
    }
}
