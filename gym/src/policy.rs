//! Policies: anything that maps a batch of observations to actions.

use crate::action::Action;
use crate::observation::Observation;
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn greedy_saturates_toward_the_target() {
        let obs = Observation {
            centres: vec![],
            vector: [0.6, -0.001],
        };
        assert_eq!(Greedy::action(&obs).components(), [1.0, -0.1]);
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
