//! The planner: a receding-horizon search over short manoeuvres, on exactly
//! what a network sees (`docs/spec.md` §2, Observation).
//!
//! Each step it predicts every visible free sphere forward at constant
//! velocity (its displacement over the last step; a sphere new to the view
//! is taken as standing still) and scores a fixed family of plans: hold one
//! of [`HEADINGS`] full-speed headings for one of [`HOLDS`] steps, then drive
//! straight at the target, over [`HORIZON`] steps. A plan that brings a
//! sphere within the collision radius is ranked by how late it does; of the
//! rest, the one with the fewest estimated steps to the target wins, less a
//! penalty for passing closer than a margin that grows with how far ahead
//! the prediction reaches. It then takes the winner's first action and plans
//! again at the next step. It reads nothing but the observation and the
//! environment's constants, and it is deterministic.

use crate::action::Action;
use crate::config::EnvConfig;
use crate::observation::Observation;
use crate::policy::Policy;

/// Full-speed headings a manoeuvre may take, evenly spaced in angle.
const HEADINGS: usize = 32;
/// How long a manoeuvre holds its heading before heading for the target,
/// steps (0: straight at the target).
const HOLDS: [u32; 6] = [0, 1, 3, 6, 12, 24];
/// Steps each plan is followed ahead.
const HORIZON: u32 = 40;
/// Clearance kept beyond the collision radius at the next step, px.
const MARGIN_PX: f64 = 5.0;
/// Clearance added per step of prediction, px: a sphere's random
/// acceleration (±0.5 px/step² per axis) moves it off its predicted line.
const MARGIN_GROWTH_PX: f64 = 0.25;
/// Estimated steps charged per px of clearance missing from the margin.
const MARGIN_COST: f64 = 0.05;
/// Cost of a plan that collides, before the credit for colliding late.
const COLLISION_COST: f64 = 1e6;

/// The receding-horizon planner for one environment's constants.
#[derive(Clone, Debug, PartialEq)]
pub struct Planner {
    fov_centre: [f64; 2],
    stage_speed: f64,
    collision_radius: f64,
    success_radius: f64,
    target_distance: f64,
    headings: Vec<[f64; 2]>,
    /// Spheres of the observation being planned: position relative to the
    /// trap and velocity, px and px/step.
    spheres: Vec<([f64; 2], [f64; 2])>,
}

impl Planner {
    /// A planner for the environment `config` describes: its field of view,
    /// stage speed, radii and target distance.
    pub fn for_config(config: &EnvConfig) -> Self {
        let headings = (0..HEADINGS)
            .map(|k| {
                let angle = std::f64::consts::TAU * k as f64 / HEADINGS as f64;
                let (s, c) = angle.sin_cos();
                let scale = c.abs().max(s.abs());
                [c / scale, s / scale]
            })
            .collect();
        Self {
            fov_centre: config.fov_px.map(|v| 0.5 * f64::from(v)),
            stage_speed: config.stage_speed_px,
            collision_radius: config.collision_radius_px,
            success_radius: config.success_radius_px,
            target_distance: config.target_distance_px,
            headings,
            spheres: Vec::new(),
        }
    }

    /// The planner's action for one observation.
    pub fn action(&mut self, observation: &Observation) -> Action {
        let target = observation
            .vector
            .map(|v| f64::from(v) * self.target_distance);
        if !target.iter().all(|v| v.is_finite()) {
            return Action::ZERO;
        }
        self.spheres.clear();
        for (k, c) in observation.centres.iter().enumerate() {
            let position = [0, 1].map(|a| f64::from(c[a]) - self.fov_centre[a]);
            let velocity = observation
                .displacement(k)
                .map_or([0.0; 2], |d| d.map(f64::from));
            self.spheres.push((position, velocity));
        }
        let mut best = (f64::INFINITY, self.toward(target, [0.0; 2]));
        for hold in HOLDS {
            let headings: &[[f64; 2]] = if hold == 0 {
                &[[0.0; 2]]
            } else {
                &self.headings
            };
            for &heading in headings {
                let (cost, first) = self.score(target, heading, hold);
                if cost < best.0 {
                    best = (cost, first);
                }
            }
        }
        let [x, y] = best.1.map(|v| v as f32);
        Action::clipped(x, y).unwrap_or(Action::ZERO)
    }

    /// The action that drives from `trap` straight at `target`, landing on
    /// it when it is within a step.
    fn toward(&self, target: [f64; 2], trap: [f64; 2]) -> [f64; 2] {
        [0, 1].map(|a| ((target[a] - trap[a]) / self.stage_speed).clamp(-1.0, 1.0))
    }

    /// The cost of holding `heading` for `hold` steps and then driving at
    /// the target, and the plan's first action.
    fn score(&self, target: [f64; 2], heading: [f64; 2], hold: u32) -> (f64, [f64; 2]) {
        let mut trap = [0.0; 2];
        let mut first = None;
        let mut shortfall = 0.0;
        for step in 1..=HORIZON {
            let action = if step <= hold {
                heading
            } else {
                self.toward(target, trap)
            };
            let first = *first.get_or_insert(action);
            trap = [0, 1].map(|a| trap[a] + action[a] * self.stage_speed);
            let t = f64::from(step);
            let margin = self.collision_radius + MARGIN_PX + MARGIN_GROWTH_PX * (t - 1.0);
            let (reach_sq, margin_sq) = (self.collision_radius.powi(2), margin * margin);
            for &(p, v) in &self.spheres {
                let dx = p[0] + v[0] * t - trap[0];
                let dy = p[1] + v[1] * t - trap[1];
                let distance_sq = dx * dx + dy * dy;
                if distance_sq < margin_sq {
                    if distance_sq <= reach_sq {
                        return (COLLISION_COST - t, first);
                    }
                    shortfall += margin - distance_sq.sqrt();
                }
            }
            let [rx, ry] = [target[0] - trap[0], target[1] - trap[1]];
            if rx.hypot(ry) <= self.success_radius {
                return (t + MARGIN_COST * shortfall, first);
            }
        }
        let [rx, ry] = [target[0] - trap[0], target[1] - trap[1]];
        let remaining = rx.abs().max(ry.abs()) / self.stage_speed;
        let first = first.unwrap_or([0.0; 2]);
        (
            f64::from(HORIZON) + remaining + MARGIN_COST * shortfall,
            first,
        )
    }
}

impl Policy for Planner {
    fn act(&mut self, observations: &[&Observation], actions: &mut [Action]) {
        for (obs, action) in observations.iter().zip(actions) {
            *action = self.action(obs);
        }
    }
}
