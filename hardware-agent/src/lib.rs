//! The hardware agent's parts: the Thorlabs APT protocol its stage driver
//! speaks to the KDC101 controllers, the driver, which keeps each stage
//! inside its limits, the calibrated pair of stages, cameras, the
//! segmentation that finds spheres in their frames, virtual obstacles, the
//! policy source, the control loop and its watchdog, episode records, and
//! the digital twin of the microscope.

pub mod apt;
pub mod camera;
pub mod config;
pub mod control;
pub mod instrument;
pub mod overlay;
pub mod policy_source;
pub mod record;
pub mod segment;
pub mod serial;
pub mod stage;
pub mod stages;
pub mod twin;
