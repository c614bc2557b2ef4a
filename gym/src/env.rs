//! The virtual optical-tweezers environment (`docs/spec.md` §2).
//!
//! The trap sits at the FOV centre; the stage moves the sample under it. Only
//! free spheres that could be in the field of view are simulated each step (see
//! `wake_schedule`); the others catch up from their own random streams when
//! they could matter, so laziness changes speed, never results.

use crate::action::Action;
use crate::config::{EnvConfig, RewardComponent};
use crate::observation::Observation;
use crate::rng::SplitMix64;
use crate::spheres::{FreeSphere, Motion};
use crate::tracking::SphereTracker;
use crate::wake_schedule::WakeSchedule;
use std::f64::consts::TAU;
use tweezer_config::ConfigError;

const COUNT_TAG: u64 = 1;
const TARGET_TAG: u64 = 2;

/// Where an episode's target lies.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Target {
    /// At the configured distance, at an angle drawn from the episode seed.
    Random,
    /// At the configured distance, at this angle in radians (0 = +x, π/2 = +y,
    /// i.e. downward in the image).
    Angle(f64),
}

/// A hand-made starting state, for scenarios and tests.
#[derive(Clone, Debug, PartialEq)]
pub struct Layout {
    /// Trap start in world px.
    pub trap: [f64; 2],
    /// Target in world px.
    pub target: [f64; 2],
    /// Free spheres: (position in world px, velocity in px/step).
    pub spheres: Vec<([f64; 2], [f64; 2])>,
}

/// How an episode ended, if it has.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Outcome {
    /// Still going.
    Running,
    /// The trap reached the target (terminated).
    Success,
    /// A free sphere entered the trap (terminated).
    Collision,
    /// The time limit passed (truncated).
    Timeout,
}

/// The reward of one step, by component (switched-off components are 0).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RewardParts {
    /// Time pressure.
    pub time: f64,
    /// Progress toward the target.
    pub carry: f64,
    /// Collision penalty.
    pub collision: f64,
    /// Success bonus.
    pub success: f64,
}

impl RewardParts {
    /// The step's reward.
    pub fn total(&self) -> f64 {
        self.time + self.carry + self.collision + self.success
    }
}

/// The result of one step, in Gymnasium's terms.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepResult {
    /// Sum of the reward components.
    pub reward: f64,
    /// The components.
    pub parts: RewardParts,
    /// The episode ended in success or collision.
    pub terminated: bool,
    /// The episode hit the time limit without terminating.
    pub truncated: bool,
    /// Which of those, if any.
    pub outcome: Outcome,
}

impl StepResult {
    /// The episode is over (terminated or truncated).
    pub fn done(&self) -> bool {
        self.terminated || self.truncated
    }
}

/// An episode that cannot start as asked.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("cannot start the episode: {0}")]
pub struct EpisodeError(pub String);

/// Stepping an episode that has already ended.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("the episode ended ({0:?}); reset the environment before stepping")]
pub struct EpisodeOver(pub Outcome);

/// One virtual environment.
#[derive(Clone, Debug)]
pub struct Env {
    config: EnvConfig,
    motion: Motion,
    seed: u64,
    spheres: Vec<FreeSphere>,
    wake: WakeSchedule,
    t: u32,
    trap: [f64; 2],
    target: [f64; 2],
    initial_distance: f64,
    outcome: Outcome,
    observation: Observation,
    tracker: SphereTracker,
}

fn distance(a: [f64; 2], b: [f64; 2]) -> f64 {
    let (dx, dy) = (a[0] - b[0], a[1] - b[1]);
    (dx * dx + dy * dy).sqrt()
}

impl Env {
    /// An environment for `config` (checked first); call a reset before
    /// stepping.
    pub fn new(config: EnvConfig) -> Result<Self, ConfigError> {
        config.validate()?;
        Ok(Self {
            motion: Motion::for_config(&config),
            seed: 0,
            spheres: Vec::with_capacity(config.max_free_spheres as usize),
            wake: WakeSchedule::new(&config),
            t: 0,
            trap: [0.0; 2],
            target: [0.0; 2],
            initial_distance: 1.0,
            outcome: Outcome::Timeout,
            observation: Observation::default(),
            tracker: SphereTracker::for_config(&config),
            config,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &EnvConfig {
        &self.config
    }

    /// The trap's start position in world px: the world's centre.
    pub fn start_position(&self) -> [f64; 2] {
        [0.5 * self.config.world_px[0], 0.5 * self.config.world_px[1]]
    }

    /// Starts the episode `seed` with a target drawn from the seed.
    pub fn reset(&mut self, seed: u64) -> &Observation {
        let angle = SplitMix64::derived(seed, TARGET_TAG).uniform(0.0, TAU);
        self.start_episode(seed, angle)
    }

    /// Starts the episode `seed` with the given target. The free spheres'
    /// number, placement and motion depend on `seed` alone, so the same seed
    /// with different targets replays identical free-sphere motion.
    pub fn reset_with_target(
        &mut self,
        seed: u64,
        target: Target,
    ) -> Result<&Observation, EpisodeError> {
        match target {
            Target::Random => Ok(self.reset(seed)),
            Target::Angle(angle) if angle.is_finite() => Ok(self.start_episode(seed, angle)),
            Target::Angle(angle) => Err(EpisodeError(format!(
                "target angle must be finite, got {angle}"
            ))),
        }
    }

    fn start_episode(&mut self, seed: u64, angle: f64) -> &Observation {
        let config = &self.config;
        let start = self.start_position();
        let count = SplitMix64::derived(seed, COUNT_TAG)
            .integer_inclusive(config.min_free_spheres, config.max_free_spheres);
        let d = config.target_distance_px;
        let target = [start[0] + d * angle.cos(), start[1] + d * angle.sin()];
        let motion = self.motion;
        let clearance = config.start_clearance_px;
        self.spheres.clear();
        self.spheres
            .extend((0..count).map(|k| FreeSphere::placed(seed, k, &motion, start, clearance)));
        self.begin(seed, start, target);
        &self.observation
    }

    /// Starts an episode from a hand-made layout; free-sphere accelerations
    /// are drawn from `seed`. Spheres must lie in the world and move within
    /// the speed limit; positions must be finite.
    pub fn reset_to_layout(
        &mut self,
        seed: u64,
        layout: &Layout,
    ) -> Result<&Observation, EpisodeError> {
        let finite = |p: [f64; 2]| p.iter().all(|v| v.is_finite());
        if !finite(layout.trap) || !finite(layout.target) {
            return Err(EpisodeError("trap and target must be finite".into()));
        }
        let [w, h] = self.config.world_px;
        let v_max = self.config.max_sphere_speed_px;
        for (k, &(pos, vel)) in layout.spheres.iter().enumerate() {
            let inside = (0.0..=w).contains(&pos[0]) && (0.0..=h).contains(&pos[1]);
            if !inside {
                return Err(EpisodeError(format!(
                    "sphere {k} at {pos:?} lies outside the {w} x {h} px world"
                )));
            }
            if !vel.iter().all(|v| v.abs() <= v_max) {
                return Err(EpisodeError(format!(
                    "sphere {k} moves at {vel:?} px/step, beyond the {v_max} px/step limit"
                )));
            }
        }
        self.spheres.clear();
        self.spheres.extend(
            layout
                .spheres
                .iter()
                .enumerate()
                .map(|(k, &(pos, vel))| FreeSphere::new(seed, k as u32, pos, vel)),
        );
        self.begin(seed, layout.trap, layout.target);
        Ok(&self.observation)
    }

    fn begin(&mut self, seed: u64, trap: [f64; 2], target: [f64; 2]) {
        self.seed = seed;
        self.t = 0;
        self.trap = trap;
        self.target = target;
        self.initial_distance = distance(trap, target).max(f64::MIN_POSITIVE);
        self.outcome = Outcome::Running;
        self.tracker.reset();
        self.wake.start(&self.spheres, trap);
        self.observe();
    }

    fn observe(&mut self) {
        let [fw, fh] = [
            f64::from(self.config.fov_px[0]),
            f64::from(self.config.fov_px[1]),
        ];
        let origin = [self.trap[0] - 0.5 * fw, self.trap[1] - 0.5 * fh];
        let radius = self.config.sphere_radius_px();
        let r2 = radius * radius;
        self.observation.centres.clear();
        for &k in self.wake.awake() {
            let p = self.spheres[k as usize].pos;
            let (x, y) = (p[0] - origin[0], p[1] - origin[1]);
            // Distance from the centre to the FOV rectangle.
            let dx = (-x).max(x - fw).max(0.0);
            let dy = (-y).max(y - fh).max(0.0);
            if dx * dx + dy * dy <= r2 {
                self.observation.centres.push([x as f32, y as f32]);
            }
        }
        self.tracker.track(
            &self.observation.centres,
            self.trap,
            &mut self.observation.displacements,
        );
        let mut v = [
            (self.target[0] - self.trap[0]) / self.initial_distance,
            (self.target[1] - self.trap[1]) / self.initial_distance,
        ];
        let magnitude = (v[0] * v[0] + v[1] * v[1]).sqrt();
        if magnitude > 1.0 {
            v = [v[0] / magnitude, v[1] / magnitude];
        }
        self.observation.vector = [v[0] as f32, v[1] as f32];
    }

    /// One step: free spheres move, then the stage, then the step is scored.
    pub fn step(&mut self, action: Action) -> Result<StepResult, EpisodeOver> {
        if self.outcome != Outcome::Running {
            return Err(EpisodeOver(self.outcome));
        }
        let before = distance(self.trap, self.target);
        let [ax, ay] = action.components();
        let speed = self.config.stage_speed_px;
        self.advance([
            self.trap[0] + f64::from(ax) * speed,
            self.trap[1] + f64::from(ay) * speed,
        ]);

        let after = distance(self.trap, self.target);
        let collided = self.wake.awake().iter().any(|&k| {
            let p = self.spheres[k as usize].pos;
            self.config
                .collides([p[0] - self.trap[0], p[1] - self.trap[1]])
        });
        self.outcome = self.config.outcome(collided, after, self.t);
        let succeeded = self.outcome == Outcome::Success;

        let c = &self.config;
        let on = |component| c.reward_on(component);
        let parts = RewardParts {
            time: if on(RewardComponent::Time) {
                c.rewards.time
            } else {
                0.0
            },
            carry: if on(RewardComponent::Carry) {
                c.rewards.carry * (before - after)
            } else {
                0.0
            },
            collision: if collided && on(RewardComponent::Collision) {
                c.rewards.collision
            } else {
                0.0
            },
            success: if succeeded && on(RewardComponent::Success) {
                c.rewards.success
            } else {
                0.0
            },
        };
        self.observe();
        Ok(StepResult {
            reward: parts.total(),
            parts,
            terminated: collided || succeeded,
            truncated: self.outcome == Outcome::Timeout,
            outcome: self.outcome,
        })
    }

    /// One step of a world whose stage is driven from outside (the hardware
    /// agent's digital twin): the free spheres move, the trap goes to `trap`
    /// (world px), and nothing is scored: whoever drives the stage decides
    /// how its episode ends. A non-finite `trap` leaves the trap where it
    /// was. Refused once the time limit has passed, since the lazy
    /// free-sphere schedule holds only within it.
    pub fn drive_to(&mut self, trap: [f64; 2]) -> Result<&Observation, EpisodeOver> {
        if self.t >= self.config.time_limit {
            return Err(EpisodeOver(Outcome::Timeout));
        }
        let finite = trap.iter().all(|v| v.is_finite());
        self.advance(if finite { trap } else { self.trap });
        self.observe();
        Ok(&self.observation)
    }

    /// Moves time on a step with the trap at `trap`.
    fn advance(&mut self, trap: [f64; 2]) {
        self.t += 1;
        self.trap = trap;
        self.wake
            .refresh(&mut self.spheres, &self.motion, self.trap, self.t);
    }

    /// The current observation (after a step that ended the episode: its
    /// final observation).
    pub fn observation(&self) -> &Observation {
        &self.observation
    }

    /// Steps taken in this episode.
    pub fn steps(&self) -> u32 {
        self.t
    }

    /// The episode seed.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// How the episode stands.
    pub fn outcome(&self) -> Outcome {
        self.outcome
    }

    /// Trap (stage) position in world px.
    pub fn trap(&self) -> [f64; 2] {
        self.trap
    }

    /// Target position in world px.
    pub fn target(&self) -> [f64; 2] {
        self.target
    }

    /// Distance from the trap's start to the target, px.
    pub fn initial_distance(&self) -> f64 {
        self.initial_distance
    }

    /// Number of free spheres in this episode.
    pub fn free_sphere_count(&self) -> usize {
        self.spheres.len()
    }

    /// Every free sphere's centre in world px at the current step, bringing
    /// the parked ones up to date first (costly: for pictures and checks,
    /// not for stepping).
    pub fn free_sphere_positions(&mut self) -> Vec<[f64; 2]> {
        let (t, motion) = (self.t, self.motion);
        self.spheres
            .iter_mut()
            .map(|s| {
                s.advance_to(t, &motion);
                s.pos
            })
            .collect()
    }
}
