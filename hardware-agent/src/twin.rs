//! The digital twin of the microscope: what the hardware agent drives when
//! there is no instrument. Two simulated KDC101s on pseudo-terminals
//! ([`TwinStages`]) move a virtual sample whose frames the twin camera
//! renders ([`TwinCamera`], [`OpticsConfig`]), so the real driver,
//! segmentation and control loop run unchanged; [`detection_quality`]
//! scores segmentation against the true centres.

mod optics;
mod quality;
mod world;

pub use optics::{Debris, OpticsConfig};
pub use quality::{DetectionQuality, MATCH_RADIUS_PX, detection_quality, episode_scene};
pub use world::{TrueCalibration, TwinCamera, TwinConfig, TwinStages};
