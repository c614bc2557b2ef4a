//! The hardware agent's parts: the Thorlabs APT protocol its stage driver
//! speaks to the KDC101 controllers, the driver, which keeps the stages
//! inside their limits, cameras, the segmentation that finds spheres in
//! their frames, and the digital twin of the microscope.

pub mod apt;
pub mod camera;
pub mod config;
pub mod segment;
pub mod serial;
pub mod stage;
pub mod twin;
