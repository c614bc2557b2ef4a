//! The theoretical maximum return: the straight run to the target with
//! nothing in the way (the dashed line of the paper's Fig. 4).

use crate::config::{EnvConfig, RewardComponent};

/// Target angles averaged over.
const ANGLES: u32 = 3600;

impl EnvConfig {
    /// The ideal episode at each of [`ANGLES`] target angles: the stage
    /// moves straight at the target as fast as its per-axis speed allows
    /// and lands within the success radius in the fewest steps; (steps,
    /// px per step).
    fn straight_runs(&self) -> impl Iterator<Item = (f64, f64)> + '_ {
        (0..ANGLES).map(|k| {
            let angle = f64::from(k) * std::f64::consts::TAU / f64::from(ANGLES);
            let speed = self.stage_speed_px / angle.cos().abs().max(angle.sin().abs());
            let steps = ((self.target_distance_px - self.success_radius_px) / speed)
                .ceil()
                .max(1.0);
            (steps, speed)
        })
    }

    /// Mean steps of the ideal episode over target angles: what a policy's
    /// successful episodes take at best.
    pub fn ideal_steps(&self) -> f64 {
        self.straight_runs().map(|(steps, _)| steps).sum::<f64>() / f64::from(ANGLES)
    }

    /// Mean return of the ideal episode over target angles, meeting no
    /// sphere (for the usual negative time reward).
    pub fn ideal_return(&self) -> f64 {
        let on = |component| self.reward_on(component);
        let distance = self.target_distance_px;
        let total: f64 = self
            .straight_runs()
            .map(|(steps, speed)| {
                // The last step starts outside the success radius.
                let mut carried = distance.min(distance - self.success_radius_px + speed);
                let mut episode = 0.0;
                if on(RewardComponent::Time) {
                    // The fewest steps; more would cost more than they carry.
                    carried = carried.min(steps * speed);
                    episode += self.rewards.time * steps;
                }
                if on(RewardComponent::Carry) {
                    episode += self.rewards.carry * carried;
                }
                if on(RewardComponent::Success) {
                    episode += self.rewards.success;
                }
                episode
            })
            .sum();
        total / f64::from(ANGLES)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_ideal_return_lies_between_the_axis_and_diagonal_runs() {
        let config = EnvConfig::default();
        // Along an axis: 98 steps of 10 px; along a diagonal: 69 of 14.1 px.
        let axis = 1000.0 + 980.0 - 98.0;
        let diagonal = 1000.0 + 69.0 * 10.0 * 2f64.sqrt() - 69.0;
        let ideal = config.ideal_return();
        assert!(axis < ideal && ideal < diagonal, "{ideal}");
        let steps = config.ideal_steps();
        assert!(69.0 < steps && steps < 98.0, "{steps}");
    }

    #[test]
    fn switched_off_components_leave_the_ideal_return() {
        let mut config = EnvConfig::default();
        config.rewards.off = vec![RewardComponent::Time, RewardComponent::Carry];
        assert_eq!(config.ideal_return(), 1000.0);
        // Untimed, the run may end closer: 27 px out minus one last step.
        config.rewards.off = vec![RewardComponent::Time, RewardComponent::Success];
        let carried = config.ideal_return();
        assert!(
            (983.0..=1000.0 - 27.0 + 10.0 * 2f64.sqrt()).contains(&carried),
            "{carried}"
        );
    }
}
