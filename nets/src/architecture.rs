//! Which network a run trains and a snapshot holds, with every
//! hyper-parameter that fixes its weights' shapes and the meaning of its
//! inputs: what snapshot metadata, checkpoints and `[learner.network]`
//! carry, and what loading compares.

use serde::{Deserialize, Serialize};
use std::fmt;
use tweezer_gym::EnvConfig;

/// The paper's CNN actor, as snapshots name it.
pub const PAPER_ARCHITECTURE: &str = "tweezer-paper-actor-v1";

/// The actor that reads sphere centres, as snapshots name it.
pub const SET_ARCHITECTURE: &str = "tweezer-set-actor-v1";

/// A network and the inputs it was built for.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Architecture {
    /// The paper's CNN on rendered binary images.
    Paper {
        /// Image height, px.
        height: usize,
        /// Image width, px.
        width: usize,
    },
    /// The set network on sphere centres.
    Set(SetShape),
}

/// How a set pools its per-sphere features.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Pooling {
    /// Masked max and mean, side by side.
    #[default]
    MaxMean,
    /// Masked max only.
    Max,
    /// Masked mean only.
    Mean,
}

impl Pooling {
    /// Its name in configs and snapshot metadata.
    pub fn name(self) -> &'static str {
        match self {
            Self::MaxMean => "max_mean",
            Self::Max => "max",
            Self::Mean => "mean",
        }
    }

    /// The pooling called `name`.
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::MaxMean, Self::Max, Self::Mean]
            .into_iter()
            .find(|p| p.name() == name)
    }

    /// Pooled features per per-sphere feature.
    pub fn factor(self) -> usize {
        match self {
            Self::MaxMean => 2,
            Self::Max | Self::Mean => 1,
        }
    }
}

/// What the set network reads of each sphere: the observation's kind.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SphereInputs {
    /// Where it is: offset from the trap and distance.
    #[default]
    Positions,
    /// Where it is and how it moved since the previous step (matched from
    /// consecutive centres), or that it is new to the view.
    Motion,
    /// Motion, and the same offset and displacement again in the frame
    /// whose x axis points at the target: the per-sphere layers then see
    /// which spheres lie ahead on the way to the target, and how they cross
    /// it, before anything is pooled.
    Goal,
}

impl SphereInputs {
    /// Its name in configs and snapshot metadata.
    pub fn name(self) -> &'static str {
        match self {
            Self::Positions => "positions",
            Self::Motion => "motion",
            Self::Goal => "goal",
        }
    }

    /// The inputs called `name`.
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::Positions, Self::Motion, Self::Goal]
            .into_iter()
            .find(|i| i.name() == name)
    }

    /// Features per sphere.
    pub fn features(self) -> usize {
        match self {
            Self::Positions => 3,
            Self::Motion => 6,
            Self::Goal => 10,
        }
    }

    /// Whether each row carries the displacement beside the position.
    pub fn has_motion(self) -> bool {
        matches!(self, Self::Motion | Self::Goal)
    }
}

/// Where the set critic joins the action to what it sees.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ActionJoin {
    /// After pooling, beside the target vector: one summary of the set
    /// judges every action.
    #[default]
    Pooled,
    /// Also in each sphere's first layer, before pooling: the per-sphere
    /// layers judge what this action does near this sphere, and the max
    /// keeps the sphere it runs into.
    PerSphere,
    /// As [`Self::PerSphere`], and each sphere's first layer also reads
    /// where the trap, held at this action, would pass it: how far ahead
    /// along the action and how far to its side. The geometry of a
    /// collision, given rather than learned.
    Approach,
}

impl ActionJoin {
    /// Its name in configs and checkpoint metadata.
    pub fn name(self) -> &'static str {
        match self {
            Self::Pooled => "pooled",
            Self::PerSphere => "per_sphere",
            Self::Approach => "approach",
        }
    }

    /// The join called `name`.
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::Pooled, Self::PerSphere, Self::Approach]
            .into_iter()
            .find(|j| j.name() == name)
    }
}

/// The frame a set network reads the scene and acts in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Frame {
    /// The stage's axes.
    #[default]
    Stage,
    /// Axes turned so that x points at the target: offsets, displacements,
    /// the target vector and the action alike. A detour is then the same
    /// function of the scene whichever way the target lies, so what one
    /// episode teaches holds at every target angle.
    Goal,
}

impl Frame {
    /// Its name in configs and snapshot metadata.
    pub fn name(self) -> &'static str {
        match self {
            Self::Stage => "stage",
            Self::Goal => "goal",
        }
    }

    /// The frame called `name`.
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::Stage, Self::Goal]
            .into_iter()
            .find(|f| f.name() == name)
    }
}

/// The set network's hyper-parameters and the field of view its inputs
/// are scaled by.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SetShape {
    /// Width of the per-sphere MLP's two layers.
    pub sphere_hidden: usize,
    /// Width of the two layers after pooling.
    pub head_hidden: usize,
    /// How the set is summarised.
    pub pooling: Pooling,
    /// Most spheres a set holds; a scene with more keeps the nearest.
    pub max_spheres: usize,
    /// The field of view (px) it was trained on: sphere positions are
    /// scaled by half its width, whatever field a later scene spans.
    pub fov_px: [u32; 2],
    /// What it reads of each sphere.
    #[serde(default)]
    pub inputs: SphereInputs,
    /// Where the critic joins the action (the actor has none to join).
    #[serde(default)]
    pub action_join: ActionJoin,
    /// Whether the critic's layers after pooling are normalised
    /// (LayerNorm before each ReLU).
    #[serde(default)]
    pub critic_layer_norm: bool,
    /// The frame it reads and acts in.
    #[serde(default)]
    pub frame: Frame,
    /// Px of displacement per unit of the motion features: the largest
    /// free-sphere speed per axis of the world it was trained in, so that
    /// they span about ±1 however fast its spheres move.
    #[serde(default = "default_motion_unit")]
    pub motion_unit_px: f32,
}

/// The motion unit of files from before it was recorded: the spec's
/// free-sphere speed, to which it was fixed.
fn default_motion_unit() -> f32 {
    EnvConfig::default().max_sphere_speed_px as f32
}

impl SetShape {
    /// The default set network (the `lean` preset's) for a `fov_px` field:
    /// 64-wide per-sphere and head layers, max and mean pooling, the 32
    /// nearest spheres, positions only, the critic's action joined after
    /// pooling, in the stage's frame, motion in units of the spec's
    /// free-sphere speed.
    pub fn new(fov_px: [u32; 2]) -> Self {
        Self {
            sphere_hidden: 64,
            head_hidden: 64,
            pooling: Pooling::MaxMean,
            max_spheres: 32,
            fov_px,
            inputs: SphereInputs::Positions,
            action_join: ActionJoin::Pooled,
            critic_layer_norm: false,
            frame: Frame::Stage,
            motion_unit_px: default_motion_unit(),
        }
    }

    /// The motion unit of a network trained in `env`: its largest
    /// free-sphere speed per axis, but never below the spec's 2 px, so that
    /// a world of still spheres (speed 0), where only the stage moves them
    /// in view, has a unit to divide by, and slower worlds keep the spec's.
    pub fn motion_unit_for(env: &EnvConfig) -> f32 {
        (env.max_sphere_speed_px as f32).max(default_motion_unit())
    }
}

impl Architecture {
    /// The name snapshots carry.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Paper { .. } => PAPER_ARCHITECTURE,
            Self::Set(_) => SET_ARCHITECTURE,
        }
    }

    /// The image resolution `(height, width)` a CNN takes; none for sets.
    pub fn image(&self) -> Option<(usize, usize)> {
        match *self {
            Self::Paper { height, width } => Some((height, width)),
            Self::Set(_) => None,
        }
    }

    /// What differs from `other`, field by field (empty when equal).
    pub fn differences(&self, other: &Self) -> Vec<String> {
        let (a, b) = (self.fields(), other.fields());
        if self.name() != other.name() {
            return vec![format!("architecture {} vs {}", self.name(), other.name())];
        }
        a.iter()
            .zip(&b)
            .filter(|(x, y)| x.1 != y.1)
            .map(|(x, y)| format!("{} {} vs {}", x.0, x.1, y.1))
            .collect()
    }

    /// Every hyper-parameter as (name, value), as snapshot metadata
    /// stores them.
    pub fn fields(&self) -> Vec<(&'static str, String)> {
        match self {
            Self::Paper { height, width } => {
                vec![("height", height.to_string()), ("width", width.to_string())]
            }
            Self::Set(s) => vec![
                ("sphere_hidden", s.sphere_hidden.to_string()),
                ("head_hidden", s.head_hidden.to_string()),
                ("pooling", s.pooling.name().to_string()),
                ("max_spheres", s.max_spheres.to_string()),
                ("fov_width", s.fov_px[0].to_string()),
                ("fov_height", s.fov_px[1].to_string()),
                ("inputs", s.inputs.name().to_string()),
                ("action_join", s.action_join.name().to_string()),
                ("critic_layer_norm", s.critic_layer_norm.to_string()),
                ("frame", s.frame.name().to_string()),
                ("motion_unit_px", s.motion_unit_px.to_string()),
            ],
        }
    }

    /// The architecture called `name` from its fields; `field` looks one
    /// up. The error names the missing or malformed field.
    pub fn from_fields<'a>(
        name: &str,
        field: impl Fn(&str) -> Option<&'a str>,
    ) -> Result<Self, ArchitectureError> {
        fn parse<'a, T: std::str::FromStr>(
            field: &impl Fn(&str) -> Option<&'a str>,
            name: &'static str,
        ) -> Result<T, ArchitectureError> {
            field(name)
                .and_then(|v| v.parse().ok())
                .ok_or(ArchitectureError::Field(name))
        }
        let shape = match name {
            PAPER_ARCHITECTURE => Self::Paper {
                height: parse(&field, "height")?,
                width: parse(&field, "width")?,
            },
            SET_ARCHITECTURE => Self::Set(SetShape {
                sphere_hidden: parse(&field, "sphere_hidden")?,
                head_hidden: parse(&field, "head_hidden")?,
                pooling: field("pooling")
                    .and_then(Pooling::from_name)
                    .ok_or(ArchitectureError::Field("pooling"))?,
                max_spheres: parse(&field, "max_spheres")?,
                fov_px: [parse(&field, "fov_width")?, parse(&field, "fov_height")?],
                // Snapshots from before motion was observed read positions.
                inputs: match field("inputs") {
                    None => SphereInputs::Positions,
                    Some(name) => {
                        SphereInputs::from_name(name).ok_or(ArchitectureError::Field("inputs"))?
                    }
                },
                // Files from before these two were chosen: pooled, no LayerNorm.
                action_join: match field("action_join") {
                    None => ActionJoin::Pooled,
                    Some(name) => ActionJoin::from_name(name)
                        .ok_or(ArchitectureError::Field("action_join"))?,
                },
                critic_layer_norm: match field("critic_layer_norm") {
                    None => false,
                    Some(_) => parse(&field, "critic_layer_norm")?,
                },
                // Files from before the frame was chosen: the stage's.
                frame: match field("frame") {
                    None => Frame::Stage,
                    Some(name) => {
                        Frame::from_name(name).ok_or(ArchitectureError::Field("frame"))?
                    }
                },
                // Files from before it was recorded: the spec's speed.
                motion_unit_px: match field("motion_unit_px") {
                    None => default_motion_unit(),
                    Some(_) => parse(&field, "motion_unit_px")?,
                },
            }),
            other => return Err(ArchitectureError::Unknown(other.to_string())),
        };
        shape.validate()?;
        Ok(shape)
    }

    /// Checks that every size is one a network can have.
    pub fn validate(&self) -> Result<(), ArchitectureError> {
        let sizes: Vec<(&'static str, usize)> = match self {
            Self::Paper { height, width } => vec![("height", *height), ("width", *width)],
            Self::Set(s) => vec![
                ("sphere_hidden", s.sphere_hidden),
                ("head_hidden", s.head_hidden),
                ("max_spheres", s.max_spheres),
                ("fov_width", s.fov_px[0] as usize),
                ("fov_height", s.fov_px[1] as usize),
            ],
        };
        for (name, value) in sizes {
            if !(1..=MAX_SIZE).contains(&value) {
                return Err(ArchitectureError::Size { name, value });
            }
        }
        if let Self::Set(s) = self
            && !(s.motion_unit_px.is_finite() && s.motion_unit_px > 0.0)
        {
            return Err(ArchitectureError::MotionUnit(s.motion_unit_px.to_string()));
        }
        if let Self::Paper { height, width } = *self {
            let min = crate::encoder::min_image_side();
            if height < min || width < min {
                return Err(ArchitectureError::ImageTooSmall { height, width, min });
            }
        }
        Ok(())
    }
}

/// Largest size any hyper-parameter may have: room for any real network,
/// and a bound on what a hostile snapshot can make a loader allocate.
const MAX_SIZE: usize = 1 << 16;

impl fmt::Display for Architecture {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.name())?;
        for (k, (name, value)) in self.fields().into_iter().enumerate() {
            let sep = if k == 0 { " (" } else { ", " };
            write!(f, "{sep}{name} {value}")?;
        }
        write!(f, ")")
    }
}

/// An architecture that cannot be built.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum ArchitectureError {
    /// No such architecture.
    #[error("unknown architecture `{0}` (known: {PAPER_ARCHITECTURE}, {SET_ARCHITECTURE})")]
    Unknown(String),
    /// A hyper-parameter is missing or malformed.
    #[error("architecture field `{0}` is missing or malformed")]
    Field(&'static str),
    /// A size is out of range.
    #[error("architecture field `{name}` = {value}: must lie in [1, 65536]")]
    Size {
        /// The field.
        name: &'static str,
        /// Its value.
        value: usize,
    },
    /// A motion unit no displacement can be divided by.
    #[error("architecture field `motion_unit_px` = {0}: must be a positive number of px")]
    MotionUnit(String),
    /// Images too small for the paper network's convolutions.
    #[error(
        "images of {width} x {height} pixels are too small for the paper network: its convolutions need at least {min} each way"
    )]
    ImageTooSmall {
        /// Image height in pixels.
        height: usize,
        /// Image width in pixels.
        width: usize,
        /// The shortest side the convolutions take.
        min: usize,
    },
}
