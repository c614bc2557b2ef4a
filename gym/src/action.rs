//! The action: stage velocity per axis.

/// Stage velocity per axis, in units of the configured stage speed: each
/// component is finite and in [-1, 1]. X grows to the right, Y downward.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Action([f32; 2]);

/// An action that cannot be driven.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ActionError {
    /// A component is NaN or infinite.
    #[error("action component {axis} is not finite ({value})")]
    NotFinite {
        /// "x" or "y".
        axis: &'static str,
        /// The value given.
        value: f32,
    },
    /// A component lies outside [-1, 1].
    #[error("action component {axis} = {value} is outside [-1, 1]")]
    OutOfRange {
        /// "x" or "y".
        axis: &'static str,
        /// The value given.
        value: f32,
    },
}

const AXES: [&str; 2] = ["x", "y"];

impl Action {
    /// Standing still.
    pub const ZERO: Self = Self([0.0; 2]);

    /// An action from components that must already lie in [-1, 1].
    pub fn new(x: f32, y: f32) -> Result<Self, ActionError> {
        for (axis, value) in AXES.into_iter().zip([x, y]) {
            if !value.is_finite() {
                return Err(ActionError::NotFinite { axis, value });
            }
            if !(-1.0..=1.0).contains(&value) {
                return Err(ActionError::OutOfRange { axis, value });
            }
        }
        Ok(Self([x, y]))
    }

    /// An action from finite components, each clipped to [-1, 1].
    pub fn clipped(x: f32, y: f32) -> Result<Self, ActionError> {
        for (axis, value) in AXES.into_iter().zip([x, y]) {
            if !value.is_finite() {
                return Err(ActionError::NotFinite { axis, value });
            }
        }
        Ok(Self([x.clamp(-1.0, 1.0), y.clamp(-1.0, 1.0)]))
    }

    /// The components `[x, y]`.
    pub fn components(self) -> [f32; 2] {
        self.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accepts_the_closed_range_and_refuses_the_rest() {
        assert!(Action::new(1.0, -1.0).is_ok());
        assert!(matches!(
            Action::new(1.01, 0.0),
            Err(ActionError::OutOfRange { axis: "x", .. })
        ));
        assert!(matches!(
            Action::new(0.0, f32::NAN),
            Err(ActionError::NotFinite { axis: "y", .. })
        ));
        assert!(Action::clipped(f32::INFINITY, 0.0).is_err());
    }

    #[test]
    fn clipped_actions_saturate_at_the_unit_box() {
        assert_eq!(
            Action::clipped(3.0, -7.5).unwrap().components(),
            [1.0, -1.0]
        );
        assert_eq!(
            Action::clipped(0.25, -0.5).unwrap().components(),
            [0.25, -0.5]
        );
    }
}
