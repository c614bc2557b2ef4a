//! Stage millimetres to image pixels and back.

use serde::{Deserialize, Serialize};

/// A stage, by the name its controller is configured under.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ImageAxis {
    /// The stage called X.
    X,
    /// The stage called Y.
    Y,
}

/// How stage travel shows in the image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Calibration {
    /// Camera pixels per µm.
    pub px_per_um: f64,
    /// The stage that moves the trap along image x.
    pub image_x: ImageAxis,
    /// Per stage (X, Y): +1 if its forward motion moves the trap toward
    /// larger image coordinates, else -1.
    pub signs: [f64; 2],
}

impl Calibration {
    /// Pixels per mm.
    fn px_per_mm(&self) -> f64 {
        self.px_per_um * 1000.0
    }

    /// Which stage (0: X, 1: Y) moves along image axis `axis` (0: x, 1: y).
    fn stage_of(&self, axis: usize) -> usize {
        match (self.image_x, axis) {
            (ImageAxis::X, a) => a,
            (ImageAxis::Y, a) => 1 - a,
        }
    }

    /// The trap's image-axis position in px, relative to where it was at
    /// stage positions `origin_mm`, for stage positions `mm` (X, Y).
    pub fn px(&self, mm: [f64; 2], origin_mm: [f64; 2]) -> [f64; 2] {
        [0, 1].map(|axis| {
            let s = self.stage_of(axis);
            self.signs[s] * (mm[s] - origin_mm[s]) * self.px_per_mm()
        })
    }

    /// Stage displacements (X, Y) in mm for an image-axis displacement in px.
    pub fn mm(&self, px: [f64; 2]) -> [f64; 2] {
        let mut mm = [0.0; 2];
        for (axis, value) in px.into_iter().enumerate() {
            let s = self.stage_of(axis);
            mm[s] = self.signs[s] * value / self.px_per_mm();
        }
        mm
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn px_and_mm_are_inverse_under_every_mapping() {
        for image_x in [ImageAxis::X, ImageAxis::Y] {
            for signs in [[1.0, 1.0], [-1.0, 1.0], [1.0, -1.0]] {
                let c = Calibration {
                    px_per_um: 10.8,
                    image_x,
                    signs,
                };
                let origin = [6.0, 5.0];
                let d = c.mm([108.0, -54.0]);
                let back = c.px([origin[0] + d[0], origin[1] + d[1]], origin);
                assert!((back[0] - 108.0).abs() < 1e-9 && (back[1] + 54.0).abs() < 1e-9);
            }
        }
        let swapped = Calibration {
            px_per_um: 10.8,
            image_x: ImageAxis::Y,
            signs: [1.0, -1.0],
        };
        // 10.8 px along image x is 1 µm of stage Y, backward.
        assert_eq!(swapped.mm([10.8, 0.0]), [0.0, -0.001]);
    }
}
