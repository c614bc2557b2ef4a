//! The virtual optical-tweezers environment of Praeger et al., its renderer,
//! vectorised stepping, sphere tracking, baseline policies (the planner
//! among them) and evaluation.
//!
//! The canonical observation is the list of sphere centres in the field of
//! view plus the target vector ([`Observation`]); [`Renderer`] turns it into
//! the binary image a network sees, the same way in every process.

mod action;
mod config;
mod env;
mod eval;
mod ideal;
mod num;
mod observation;
mod planner;
mod policy;
mod render;
mod rng;
mod seeds;
mod spheres;
mod step_record;
mod tracking;
mod trajectory;
mod vec_env;
mod wake_schedule;

pub use action::{Action, ActionError};
pub use config::{EnvConfig, ImageConfig, RewardComponent, RewardConfig};
pub use env::{Env, EpisodeError, EpisodeOver, Layout, Outcome, RewardParts, StepResult, Target};
pub use eval::{EvalSummary, evaluate};
pub use observation::{Observation, ObservationBounds, ObservationError, displacement_at};
pub use planner::Planner;
pub use policy::{Baseline, Greedy, Policy, UniformRandom};
pub use render::{Frame, Pixel, Renderer, SizeMismatch};
pub use rng::SplitMix64;
pub use seeds::{Seeds, SeedsError};
pub use spheres::{FreeSphere, Motion};
pub use step_record::{EpisodeEnd, StepBounds, StepRecord};
pub use tracking::SphereTracker;
pub use trajectory::{RecordError, Trajectory, record};
pub use vec_env::{ActionCountMismatch, EpisodeStats, RandomSteps, Slot, VecEnv};
