//! The microscope's two stages as one: image-axis velocities in, trap
//! positions in world px out, through the calibration (px per µm, which
//! stage moves the sample along image x, and each stage's sign).

mod calibration;
mod driver;
mod shared_port;

pub use calibration::{Calibration, ImageAxis};
pub use driver::{StagePair, StagesError};
pub use shared_port::{SharedPort, Stopper};

use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use tweezer_config::{ConfigError, in_range};

/// The `[stages]` table: the two KDC101 controllers and how they map onto
/// the image.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StagesConfig {
    /// Serial port of the controller of the stage called X.
    pub x_port: PathBuf,
    /// Serial port of the controller of the stage called Y.
    pub y_port: PathBuf,
    /// Serial number of stage X's controller, when known: any other
    /// controller found on `x_port` (the ports swapped, say) is refused.
    pub x_serial: Option<u32>,
    /// The same for stage Y.
    pub y_serial: Option<u32>,
    /// Refuse to drive a stage that has not been homed since its
    /// controller powered up (`hardware-agent home` homes both).
    pub require_homed: bool,
    /// Camera pixels per µm of stage travel.
    pub px_per_um: f64,
    /// Which stage moves the sample along the image's x axis ("x" or "y").
    pub image_x: ImageAxis,
    /// +1 if moving stage X forward moves the trap toward larger image
    /// coordinates along its axis (the sample's features toward smaller
    /// ones), else -1.
    pub x_sign: f64,
    /// The same for stage Y.
    pub y_sign: f64,
    /// Soft travel limits, mm, the same for both stages (inside the Z8's
    /// 12 mm).
    pub min_mm: f64,
    /// Upper soft travel limit, mm.
    pub max_mm: f64,
    /// Fastest speed ever commanded, mm/s.
    pub max_speed_mm_s: f64,
    /// Acceleration of every move, mm/s².
    pub acceleration_mm_s2: f64,
    /// Lost motion on reversal, µm, taken up by the driver.
    pub backlash_um: f64,
    /// Longest wait for a controller's reply, ms.
    pub reply_timeout_ms: u64,
}

impl Default for StagesConfig {
    fn default() -> Self {
        Self {
            x_port: PathBuf::from("/dev/ttyUSB0"),
            y_port: PathBuf::from("/dev/ttyUSB1"),
            x_serial: None,
            y_serial: None,
            require_homed: true,
            px_per_um: 10.8,
            image_x: ImageAxis::X,
            x_sign: 1.0,
            y_sign: 1.0,
            min_mm: 0.5,
            max_mm: 11.5,
            max_speed_mm_s: 2.6,
            acceleration_mm_s2: 1.5,
            backlash_um: 8.0,
            reply_timeout_ms: 500,
        }
    }
}

impl StagesConfig {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), ConfigError> {
        for (name, value, lo, hi) in [
            ("px_per_um", self.px_per_um, 0.01, 1000.0),
            ("min_mm", self.min_mm, 0.0, 12.0),
            ("max_mm", self.max_mm, 0.0, 12.0),
            ("max_speed_mm_s", self.max_speed_mm_s, 1e-4, 2.6),
            ("acceleration_mm_s2", self.acceleration_mm_s2, 1e-3, 4.0),
            ("backlash_um", self.backlash_um, 0.0, 100.0),
        ] {
            in_range(name, value, lo, hi)?;
        }
        if self.min_mm >= self.max_mm {
            return Err(ConfigError::invalid(
                "min_mm",
                format!("{} must be below max_mm = {}", self.min_mm, self.max_mm),
            ));
        }
        for (name, sign) in [("x_sign", self.x_sign), ("y_sign", self.y_sign)] {
            if sign != 1.0 && sign != -1.0 {
                return Err(ConfigError::invalid(
                    name,
                    format!("{sign} must be 1 or -1"),
                ));
            }
        }
        if !(1..=60_000).contains(&self.reply_timeout_ms) {
            return Err(ConfigError::invalid(
                "reply_timeout_ms",
                format!("{} must lie in [1, 60000]", self.reply_timeout_ms),
            ));
        }
        if self.x_port == self.y_port {
            return Err(ConfigError::invalid(
                "y_port",
                format!("x_port and y_port are both {}", self.x_port.display()),
            ));
        }
        Ok(())
    }

    /// The calibration these settings describe.
    pub fn calibration(&self) -> Calibration {
        Calibration {
            px_per_um: self.px_per_um,
            image_x: self.image_x,
            signs: [self.x_sign, self.y_sign],
        }
    }
}
