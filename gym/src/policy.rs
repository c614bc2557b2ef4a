//! Policies: anything that maps a batch of observations to actions.

use crate::action::Action;
use crate::config::EnvConfig;
use crate::observation::Observation;
use crate::planner::Planner;
use crate::rng::SplitMix64;

/// Chooses actions for a batch of observations at once (networks run
/// batched; simple policies just loop).
pub trait Policy {
    /// Writes one action per observation into `actions` (same length).
    fn act(&mut self, observations: &[&Observation], actions: &mut [Action]);
}

/// Drives straight at the target, blind to spheres:
/// action = clip(100 · vector, -1, 1).
#[derive(Clone, Copy, Debug, Default)]
pub struct Greedy;

impl Greedy {
    /// The greedy action for one observation.
    pub fn action(observation: &Observation) -> Action {
        let [x, y] = observation.vector;
        // A valid observation's vector is finite; a NaN one stands still.
        Action::clipped(100.0 * x, 100.0 * y).unwrap_or(Action::ZERO)
    }
}

impl Policy for Greedy {
    fn act(&mut self, observations: &[&Observation], actions: &mut [Action]) {
        for (obs, action) in observations.iter().zip(actions) {
            *action = Self::action(obs);
        }
    }
}

/// Uniformly random actions in [-1, 1]², from a seeded stream.
#[derive(Clone, Debug)]
pub struct UniformRandom(SplitMix64);

impl UniformRandom {
    /// A random policy whose actions are fixed by `seed`.
    pub fn new(seed: u64) -> Self {
        Self(SplitMix64::derived(seed, 0x5eed))
    }

    /// The next random action.
    pub fn sample(&mut self) -> Action {
        let x = self.0.uniform(-1.0, 1.0) as f32;
        let y = self.0.uniform(-1.0, 1.0) as f32;
        Action::clipped(x, y).expect("uniform draws are finite")
    }
}

impl Policy for UniformRandom {
    fn act(&mut self, _observations: &[&Observation], actions: &mut [Action]) {
        for action in actions {
            *action = self.sample();
        }
    }
}

/// The policies that need no training, by the names users give them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Baseline {
    /// [`Greedy`]: straight at the target.
    Greedy,
    /// [`UniformRandom`] from seed 0.
    Random,
    /// [`Planner`]: a receding-horizon search on the same observation.
    Planner,
}

impl Baseline {
    /// Every baseline, in the order reports list them.
    pub const ALL: [Self; 3] = [Self::Greedy, Self::Random, Self::Planner];

    /// The baseline called `name`, if any.
    pub fn named(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|b| b.name() == name)
    }

    /// Its name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Greedy => "greedy",
            Self::Random => "random",
            Self::Planner => "planner",
        }
    }

    /// The names, for messages: "`greedy`, `random`, `planner`".
    pub fn names() -> String {
        Self::ALL.map(|b| format!("`{}`", b.name())).join(", ")
    }

    /// The policy, for observations of `config`.
    pub fn policy(self, config: &EnvConfig) -> Box<dyn Policy + Send> {
        match self {
            Self::Greedy => Box::new(Greedy),
            Self::Random => Box::new(UniformRandom::new(0)),
            Self::Planner => Box::new(Planner::for_config(config)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn greedy_saturates_toward_the_target() {
        let obs = Observation {
            vector: [0.6, -0.001],
            ..Observation::default()
        };
        assert_eq!(Greedy::action(&obs).components(), [1.0, -0.1]);
    }

    #[test]
    fn baselines_are_found_by_their_names() {
        for b in Baseline::ALL {
            assert_eq!(Baseline::named(b.name()), Some(b));
        }
        assert_eq!(Baseline::named("planer"), None);
        assert_eq!(Baseline::names(), "`greedy`, `random`, `planner`");
    }

    #[test]
    fn random_actions_are_in_range_and_seeded() {
        let mut a = UniformRandom::new(1);
        let mut b = UniformRandom::new(1);
        for _ in 0..1000 {
            let x = a.sample();
            assert_eq!(x, b.sample());
            assert!(x.components().iter().all(|c| (-1.0..=1.0).contains(c)));
        }
    }
}
