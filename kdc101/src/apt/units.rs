//! Device units of a KDC101 driving a Z8-series actuator: positions in
//! encoder counts, velocities and accelerations scaled by the controller's
//! servo period T = 2048 / 6 MHz (APT protocol, "KDC101 units").

/// The KDC101's servo loop period, s.
const SERVO_PERIOD_S: f64 = 2048.0 / 6.0e6;
/// The fixed-point scale of velocities and accelerations.
const SCALE: f64 = 65536.0;

/// Conversions between mm and device units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Z8Units {
    /// Encoder counts per mm of travel.
    pub counts_per_mm: f64,
}

impl Default for Z8Units {
    /// Z8-series actuators: 512 counts per motor turn × 67.49 gearbox,
    /// 1 mm lead screw.
    fn default() -> Self {
        Self {
            counts_per_mm: 34_554.96,
        }
    }
}

impl Z8Units {
    /// Encoder counts for a position in mm (saturating at the counter's
    /// range).
    pub fn counts(&self, mm: f64) -> i32 {
        (mm * self.counts_per_mm).round() as i32
    }

    /// Position in mm of an encoder count.
    pub fn mm(&self, counts: i32) -> f64 {
        f64::from(counts) / self.counts_per_mm
    }

    /// Device velocity for mm/s.
    pub fn velocity(&self, mm_per_s: f64) -> i32 {
        (mm_per_s * self.counts_per_mm * SERVO_PERIOD_S * SCALE).round() as i32
    }

    /// mm/s of a device velocity.
    pub fn mm_per_s(&self, velocity: i32) -> f64 {
        f64::from(velocity) / (self.counts_per_mm * SERVO_PERIOD_S * SCALE)
    }

    /// Device acceleration for mm/s².
    pub fn acceleration(&self, mm_per_s2: f64) -> i32 {
        (mm_per_s2 * self.counts_per_mm * SERVO_PERIOD_S * SERVO_PERIOD_S * SCALE).round() as i32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn z8_units_match_the_protocol_tables() {
        let z8 = Z8Units::default();
        assert_eq!(z8.counts(1.0), 34_555);
        assert!((z8.mm(34_555) - 1.0).abs() < 1e-4);
        // The protocol's KDC101/Z8 table: 1 mm/s = 772,981 units, 1 mm/s² = 264.
        assert_eq!(z8.velocity(1.0), 772_981);
        assert_eq!(z8.acceleration(1.0), 264);
        // The paper's stages: 2.6 mm/s at most.
        assert!((z8.mm_per_s(z8.velocity(2.6)) - 2.6).abs() < 1e-6);
        assert_eq!(z8.counts(1e9), i32::MAX, "saturates");
    }
}
