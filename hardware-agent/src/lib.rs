//! The hardware agent's parts: the calibration it measures, virtual
//! obstacles, the policy source, the control loop and its watchdog, episode
//! records, the instrument (stages, camera and segmentation as one), and
//! the digital twin of the microscope.
//! The KDC101 driver lives in `kdc101`, cameras and segmentation in
//! `tweezer-vision`.

pub mod calibration;
pub mod config;
pub mod control;
pub mod instrument;
pub mod overlay;
pub mod policy_source;
pub mod record;
pub mod twin;
