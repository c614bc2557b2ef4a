//! The paper's pictures: reward curves (Fig. 4) as SVG, episode scenes
//! (Figs. 5 and 6) and instrument episodes (Figs. 7 and 8) as PNG, and the
//! episodes of a policy drawn that way.

mod pictures;
mod rewards;
mod scenes;

pub use pictures::{Pictures, draw_episodes};
pub use rewards::{Curve, RewardFigure, reward_figure, rolling_mean};
pub use scenes::{FieldEpisode, episode_figure, field_figure, targets_figure};

/// A picture that could not be drawn or written.
#[derive(Debug, thiserror::Error)]
pub enum FigureError {
    /// Nothing to draw.
    #[error("no trajectory to draw")]
    Empty,
    /// The drawing backend failed (e.g. the file cannot be written).
    #[error("cannot draw {path}: {reason}")]
    Draw {
        /// The picture's path.
        path: String,
        /// The backend's reason.
        reason: String,
    },
    /// An episode could not be recorded.
    #[error(transparent)]
    Record(#[from] tweezer_gym::RecordError),
    /// The output directory cannot be created.
    #[error("cannot create {path}: {reason}")]
    Directory {
        /// The directory.
        path: String,
        /// The operating system's reason.
        reason: String,
    },
}
