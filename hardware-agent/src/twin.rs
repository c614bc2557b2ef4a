//! The digital twin of the microscope: what the hardware agent drives when
//! there is no instrument. Its camera renders frames ([`OpticsConfig`]) of
//! the spheres of a virtual episode, and [`detection_quality`] scores
//! segmentation against their true centres.

mod optics;
mod quality;
mod stage_server;

pub use optics::{Debris, OpticsConfig};
pub use quality::{DetectionQuality, MATCH_RADIUS_PX, detection_quality, episode_scene};
pub use stage_server::{ControllerGuard, Fault, TwinStage};
