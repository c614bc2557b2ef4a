//! The augmented environment's virtual obstacles (`docs/spec.md` §6): discs of
//! the sphere diameter in world coordinates, merged with the detected spheres
//! before rendering so the policy treats both alike. Walls (rows of touching
//! discs, e.g. the gates of the paper's Fig. 8 maze) and a keep-out zone inside
//! the stages' travel limits are made of the same discs.

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use tweezer_config::{ConfigError, in_range};

/// The `[overlay]` table.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OverlayConfig {
    /// Virtual obstacles to load at start (an overlay file), if any.
    pub file: Option<PathBuf>,
    /// Width of the keep-out zone inside the soft travel limits, µm: a wall
    /// of virtual discs runs this far inside them (0: none).
    pub keep_out_um: f64,
}

impl OverlayConfig {
    /// Checks the keep-out width.
    pub fn validate(&self) -> Result<(), ConfigError> {
        in_range("keep_out_um", self.keep_out_um, 0.0, 5000.0)
    }
}

/// An overlay file: obstacles in µm along the image axes, relative to where
/// the trap stood when the agent connected to the stages.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OverlaySpec {
    /// Single discs: their centres.
    pub discs_um: Vec<[f64; 2]>,
    /// Walls: straight rows of touching discs.
    pub walls: Vec<Wall>,
}

/// A straight wall of discs from one end to the other.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Wall {
    /// One end, µm.
    pub from_um: [f64; 2],
    /// The other end, µm.
    pub to_um: [f64; 2],
}

/// Most discs an overlay may hold.
pub const MAX_DISCS: usize = 100_000;

/// An overlay that cannot be used.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum OverlayError {
    /// The file cannot be read or parsed.
    #[error("overlay file {path}: {reason}")]
    File {
        /// The file.
        path: String,
        /// Why.
        reason: String,
    },
    /// A coordinate is not finite or lies too far away.
    #[error("overlay {what} at {value:?} µm: coordinates must be finite and within ±1e6 µm")]
    Coordinate {
        /// Which item.
        what: String,
        /// Its value.
        value: [f64; 2],
    },
    /// Too many discs.
    #[error("overlay holds {0} discs, more than {MAX_DISCS}")]
    TooLarge(usize),
}

impl OverlaySpec {
    /// Reads an overlay file (TOML).
    pub fn from_file(path: &Path) -> Result<Self, OverlayError> {
        let error = |reason: String| OverlayError::File {
            path: path.display().to_string(),
            reason,
        };
        let text = std::fs::read_to_string(path).map_err(|e| error(e.to_string()))?;
        toml::from_str(&text).map_err(|e| error(e.to_string()))
    }
}

/// Virtual obstacles as disc centres in world px.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Overlay {
    discs: Vec<[f64; 2]>,
    keep_out: Option<KeepOut>,
}

/// A rectangle (world px) the trap must stay inside, drawn as walls.
#[derive(Clone, Copy, Debug, PartialEq)]
struct KeepOut {
    min: [f64; 2],
    max: [f64; 2],
}

impl Overlay {
    /// The discs of `spec`, spaced `radius_px` apart along walls.
    pub fn new(spec: &OverlaySpec, px_per_um: f64, radius_px: f64) -> Result<Self, OverlayError> {
        let check = |what: String, p: [f64; 2]| {
            if p.iter().all(|v| v.is_finite() && v.abs() <= 1e6) {
                Ok([p[0] * px_per_um, p[1] * px_per_um])
            } else {
                Err(OverlayError::Coordinate { what, value: p })
            }
        };
        let mut discs = Vec::new();
        for (k, &d) in spec.discs_um.iter().enumerate() {
            discs.push(check(format!("disc {k}"), d)?);
        }
        for (k, wall) in spec.walls.iter().enumerate() {
            let a = check(format!("wall {k}"), wall.from_um)?;
            let b = check(format!("wall {k}"), wall.to_um)?;
            let length = (b[0] - a[0]).hypot(b[1] - a[1]);
            let count = (length / radius_px).ceil() as usize + 1;
            if discs.len() + count > MAX_DISCS {
                return Err(OverlayError::TooLarge(discs.len() + count));
            }
            for i in 0..count {
                let f = if count > 1 {
                    i as f64 / (count - 1) as f64
                } else {
                    0.0
                };
                discs.push([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])]);
            }
        }
        if discs.len() > MAX_DISCS {
            return Err(OverlayError::TooLarge(discs.len()));
        }
        Ok(Self {
            discs,
            keep_out: None,
        })
    }

    /// Adds walls `margin_px` inside the rectangle `travel` (world px, min
    /// and max corners), so the policy steers clear of the travel limits.
    pub fn with_keep_out(mut self, travel: [[f64; 2]; 2], margin_px: f64) -> Self {
        let [lo, hi] = travel;
        self.keep_out = Some(KeepOut {
            min: [lo[0] + margin_px, lo[1] + margin_px],
            max: [hi[0] - margin_px, hi[1] - margin_px],
        });
        self
    }

    /// The obstacle discs' centres (keep-out walls excluded).
    pub fn discs(&self) -> &[[f64; 2]] {
        &self.discs
    }

    /// Appends to `out` every virtual disc that shows in a field of view of
    /// `fov_px` around the trap at `trap` (world px), in FOV px. `radius_px`
    /// is the disc radius and the spacing of keep-out walls.
    pub fn visible(
        &self,
        trap: [f64; 2],
        fov_px: [f64; 2],
        radius_px: f64,
        out: &mut Vec<[f32; 2]>,
    ) {
        let origin = [trap[0] - 0.5 * fov_px[0], trap[1] - 0.5 * fov_px[1]];
        let lo = [origin[0] - radius_px, origin[1] - radius_px];
        let hi = [
            origin[0] + fov_px[0] + radius_px,
            origin[1] + fov_px[1] + radius_px,
        ];
        let inside = |p: [f64; 2]| (0..2).all(|a| p[a] >= lo[a] && p[a] <= hi[a]);
        let mut push = |p: [f64; 2]| {
            if inside(p) {
                out.push([(p[0] - origin[0]) as f32, (p[1] - origin[1]) as f32]);
            }
        };
        for &d in &self.discs {
            push(d);
        }
        if let Some(k) = self.keep_out {
            // Each wall: a fixed coordinate on one axis; discs at multiples
            // of the radius along the other, within the view and the zone.
            for axis in 0..2 {
                let other = 1 - axis;
                let from = lo[other].max(k.min[other]);
                let to = hi[other].min(k.max[other]);
                for fixed in [k.min[axis], k.max[axis]] {
                    if fixed < lo[axis] || fixed > hi[axis] || from > to {
                        continue;
                    }
                    let mut s = (from / radius_px).ceil() * radius_px;
                    while s <= to {
                        let mut p = [0.0; 2];
                        p[axis] = fixed;
                        p[other] = s;
                        push(p);
                        s += radius_px;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const R: f64 = 27.0;
    const FOV: [f64; 2] = [1280.0, 1024.0];

    fn visible(overlay: &Overlay, trap: [f64; 2]) -> Vec<[f32; 2]> {
        let mut out = Vec::new();
        overlay.visible(trap, FOV, R, &mut out);
        out
    }

    #[test]
    fn discs_and_walls_land_in_the_field_of_view_where_they_are() {
        let spec: OverlaySpec = toml::from_str(
            "discs_um = [[10.0, 0.0], [1000.0, 0.0]]\n\
             [[walls]]\nfrom_um = [-5.0, 20.0]\nto_um = [5.0, 20.0]\n",
        )
        .unwrap();
        let overlay = Overlay::new(&spec, 10.8, R).unwrap();
        // The wall is 108 px long: 5 discs 27 px apart.
        assert_eq!(overlay.discs().len(), 2 + 5);
        let seen = visible(&overlay, [0.0, 0.0]);
        // The far disc (10.8 mm away) is out of view; the near one sits
        // 108 px right of the FOV centre.
        assert_eq!(seen.len(), 6);
        assert_eq!(seen[0], [748.0, 512.0]);
        assert!(seen[1..].iter().all(|c| (c[1] - 728.0).abs() < 1e-3));
        // Moving the trap right moves everything left in view.
        let moved = visible(&overlay, [100.0, 0.0]);
        assert_eq!(moved[0], [648.0, 512.0]);
    }

    #[test]
    fn the_keep_out_wall_shows_only_near_the_limits() {
        let overlay =
            Overlay::default().with_keep_out([[-5000.0, -5000.0], [5000.0, 5000.0]], 100.0);
        assert!(visible(&overlay, [0.0, 0.0]).is_empty());
        // Near the right limit the wall runs down the view at x = 4900.
        let seen = visible(&overlay, [4500.0, 0.0]);
        assert!(!seen.is_empty());
        for c in &seen {
            assert!((c[0] - (4900.0 - 4500.0 + 640.0)).abs() < 1e-3, "{c:?}");
            assert!((-R as f32..=1024.0 + R as f32).contains(&c[1]));
        }
        // Consecutive discs touch: no gap a sphere could pass.
        let mut ys: Vec<f32> = seen.iter().map(|c| c[1]).collect();
        ys.sort_by(f32::total_cmp);
        assert!(ys.windows(2).all(|w| w[1] - w[0] <= R as f32 + 1e-3));
    }

    #[test]
    fn bad_overlays_are_named() {
        let spec = OverlaySpec {
            discs_um: vec![[f64::NAN, 0.0]],
            walls: vec![],
        };
        assert!(matches!(
            Overlay::new(&spec, 10.8, R),
            Err(OverlayError::Coordinate { .. })
        ));
        let huge = OverlaySpec {
            discs_um: vec![],
            walls: vec![Wall {
                from_um: [-1e6, 0.0],
                to_um: [1e6, 0.0],
            }],
        };
        assert!(matches!(
            Overlay::new(&huge, 10.8, R),
            Err(OverlayError::TooLarge(_))
        ));
    }
}
