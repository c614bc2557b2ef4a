//! The canonical observation: sphere centres in the field of view plus the
//! target vector. Pixels are made from it by the renderer, right before a
//! network sees them.

use crate::config::EnvConfig;
use crate::tracking::SphereTracker;

/// What a policy observes at one step, identical in the virtual, physical and
/// augmented environments.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Observation {
    /// Centres of the free spheres in or overlapping the field of view, in
    /// full-resolution FOV px (x right, y down). The trapped sphere is not
    /// listed: it is always at the FOV centre and the renderer draws it.
    pub centres: Vec<[f32; 2]>,
    /// Each centre's move since the previous step relative to the sample,
    /// px, matched from consecutive centres by [`SphereTracker`]; `None` for
    /// a sphere new to the field of view. Empty where no motion is known
    /// (every sphere then counts as new), else one per centre.
    ///
    /// [`SphereTracker`]: crate::SphereTracker
    pub displacements: Vec<Option<[f32; 2]>>,
    /// (target - trap) / initial displacement, magnitude clipped to 1.
    pub vector: [f32; 2],
}

/// Sphere `index`'s displacement in `displacements`, as an observation
/// lists them: `None` for a sphere new to the view, and for every sphere
/// where the list is empty (no motion known).
pub fn displacement_at(displacements: &[Option<[f32; 2]>], index: usize) -> Option<[f32; 2]> {
    displacements.get(index).copied().flatten()
}

/// Limits a well-formed observation stays within.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ObservationBounds {
    /// FOV size in px.
    pub fov_px: [f32; 2],
    /// How far outside the FOV a listed centre may lie (the sphere radius).
    pub margin_px: f32,
    /// Most centres an observation may list.
    pub max_centres: usize,
    /// Largest displacement per axis, px: a match farther than the tracker's
    /// gate is never made.
    pub max_displacement_px: f32,
}

/// Why an observation is malformed.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ObservationError {
    /// Too many centres.
    #[error("observation lists {count} centres, more than the {max} allowed")]
    TooManyCentres {
        /// How many were given.
        count: usize,
        /// The limit.
        max: usize,
    },
    /// A centre coordinate is NaN or infinite.
    #[error("centre {index} is not finite ({x}, {y})")]
    CentreNotFinite {
        /// Its position in the list.
        index: usize,
        /// x as given.
        x: f32,
        /// y as given.
        y: f32,
    },
    /// A centre lies too far outside the field of view.
    #[error(
        "centre {index} at ({x}, {y}) px lies outside the field of view {w}x{h} px by more than {margin} px"
    )]
    CentreOutside {
        /// Its position in the list.
        index: usize,
        /// x as given.
        x: f32,
        /// y as given.
        y: f32,
        /// FOV width.
        w: f32,
        /// FOV height.
        h: f32,
        /// Allowed margin.
        margin: f32,
    },
    /// The displacements are neither absent nor one per centre.
    #[error(
        "observation lists {displacements} displacements for {centres} centres: give none or one per centre"
    )]
    DisplacementCount {
        /// Displacements given.
        displacements: usize,
        /// Centres given.
        centres: usize,
    },
    /// A displacement is NaN, infinite, or longer than a step could move.
    #[error("displacement {index} ({x}, {y}) px must be finite and at most {max} px on each axis")]
    BadDisplacement {
        /// Its position in the list.
        index: usize,
        /// x as given.
        x: f32,
        /// y as given.
        y: f32,
        /// The largest move allowed per axis.
        max: f32,
    },
    /// The target vector is NaN, infinite or longer than 1.
    #[error("target vector ({x}, {y}) must be finite with magnitude at most 1")]
    BadVector {
        /// x as given.
        x: f32,
        /// y as given.
        y: f32,
    },
}

impl ObservationBounds {
    /// The bounds an environment with this configuration produces.
    pub fn for_config(config: &EnvConfig) -> Self {
        let fov_w = config.fov_px[0] as f32;
        let fov_h = config.fov_px[1] as f32;
        let radius = config.sphere_radius_px() as f32;
        // Disjoint discs cannot pack denser than one per (diameter²) of the
        // FOV grown by a radius on every side; twice that is room to spare
        // for overlapping physical detections and virtual obstacles.
        let per_side = |side: f32| ((side + 2.0 * radius) / radius).ceil() as usize;
        Self {
            fov_px: [fov_w, fov_h],
            margin_px: radius,
            max_centres: per_side(fov_w) * per_side(fov_h),
            max_displacement_px: SphereTracker::for_config(config).gate_px(),
        }
    }
}

impl Observation {
    /// Sphere `index`'s displacement since the previous step, px, if it was
    /// matched.
    pub fn displacement(&self, index: usize) -> Option<[f32; 2]> {
        displacement_at(&self.displacements, index)
    }

    /// Checks that every value is finite and within `bounds`.
    pub fn validate(&self, bounds: &ObservationBounds) -> Result<(), ObservationError> {
        if self.centres.len() > bounds.max_centres {
            return Err(ObservationError::TooManyCentres {
                count: self.centres.len(),
                max: bounds.max_centres,
            });
        }
        let [w, h] = bounds.fov_px;
        let margin = bounds.margin_px;
        for (index, &[x, y]) in self.centres.iter().enumerate() {
            if !(x.is_finite() && y.is_finite()) {
                return Err(ObservationError::CentreNotFinite { index, x, y });
            }
            if x < -margin || x > w + margin || y < -margin || y > h + margin {
                return Err(ObservationError::CentreOutside {
                    index,
                    x,
                    y,
                    w,
                    h,
                    margin,
                });
            }
        }
        if !self.displacements.is_empty() && self.displacements.len() != self.centres.len() {
            return Err(ObservationError::DisplacementCount {
                displacements: self.displacements.len(),
                centres: self.centres.len(),
            });
        }
        let max = bounds.max_displacement_px;
        for (index, d) in self.displacements.iter().enumerate() {
            if let &Some([x, y]) = d
                && !(x.is_finite() && y.is_finite() && x.abs() <= max && y.abs() <= max)
            {
                return Err(ObservationError::BadDisplacement { index, x, y, max });
            }
        }
        let [x, y] = self.vector;
        // A vector clipped to magnitude 1 in f32 may exceed 1 by rounding.
        if !(x.is_finite() && y.is_finite()) || x.hypot(y) > 1.0 + 1e-5 {
            return Err(ObservationError::BadVector { x, y });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bounds() -> ObservationBounds {
        ObservationBounds::for_config(&EnvConfig::default())
    }

    #[test]
    fn a_typical_observation_is_valid() {
        let obs = Observation {
            centres: vec![[0.0, 0.0], [-27.0, 1051.0], [640.5, 512.25]],
            displacements: vec![None, Some([1.5, -2.0]), Some([0.0, 0.0])],
            vector: [0.6, -0.8],
        };
        obs.validate(&bounds()).unwrap();
    }

    #[test]
    fn malformed_observations_are_named() {
        let bad = |centres: Vec<[f32; 2]>, vector| Observation {
            centres,
            vector,
            ..Observation::default()
        };
        let b = bounds();
        assert!(matches!(
            bad(vec![[f32::NAN, 1.0]], [0.0, 0.0]).validate(&b),
            Err(ObservationError::CentreNotFinite { index: 0, .. })
        ));
        assert!(matches!(
            bad(vec![[1.0, 1.0], [1308.0, 1.0]], [0.0, 0.0]).validate(&b),
            Err(ObservationError::CentreOutside { index: 1, .. })
        ));
        assert!(matches!(
            bad(vec![], [0.9, 0.9]).validate(&b),
            Err(ObservationError::BadVector { .. })
        ));
        assert!(matches!(
            bad(vec![], [f32::INFINITY, 0.0]).validate(&b),
            Err(ObservationError::BadVector { .. })
        ));
        assert!(matches!(
            bad(vec![[1.0, 1.0]; b.max_centres + 1], [0.0, 0.0]).validate(&b),
            Err(ObservationError::TooManyCentres { .. })
        ));
        let moving = |displacements| Observation {
            centres: vec![[1.0, 1.0], [2.0, 2.0]],
            displacements,
            vector: [0.0, 0.0],
        };
        assert!(matches!(
            moving(vec![None]).validate(&b),
            Err(ObservationError::DisplacementCount {
                displacements: 1,
                centres: 2
            })
        ));
        assert!(matches!(
            moving(vec![None, Some([f32::NAN, 0.0])]).validate(&b),
            Err(ObservationError::BadDisplacement { index: 1, .. })
        ));
        assert!(matches!(
            moving(vec![Some([0.0, 20.0]), None]).validate(&b),
            Err(ObservationError::BadDisplacement { index: 0, .. })
        ));
        moving(vec![]).validate(&b).unwrap();
    }
}
