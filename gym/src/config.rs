//! The environment's configuration: `docs/spec.md` §1–2 as typed defaults,
//! loadable from TOML and validated with errors that name the offending field.

use serde::{Deserialize, Serialize};
use std::path::Path;
use tweezer_config::{ConfigError, read_toml};

use crate::env::Outcome;

/// Everything that defines the virtual environment. Defaults are `docs/spec.md`
/// §2.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EnvConfig {
    /// Camera field of view, full-resolution px (width, height).
    pub fov_px: [u32; 2],
    /// World rectangle in px (width, height), centred on the trap's start.
    pub world_px: [f64; 2],
    /// Microsphere diameter in px (54 px = 5 µm).
    pub sphere_diameter_px: f64,
    /// Fewest free spheres in an episode.
    pub min_free_spheres: u32,
    /// Most free spheres in an episode.
    pub max_free_spheres: u32,
    /// Largest random acceleration per axis, px/step².
    pub brownian_accel_px: f64,
    /// Largest free-sphere speed per axis, px/step.
    pub max_sphere_speed_px: f64,
    /// No free sphere centre starts within this distance of the trap, px.
    pub start_clearance_px: f64,
    /// Stage speed per axis at action ±1, px/step.
    pub stage_speed_px: f64,
    /// Distance from the trap's start to the target, px.
    pub target_distance_px: f64,
    /// Success: trap centre within this distance of the target (inclusive), px.
    pub success_radius_px: f64,
    /// Collision: a free sphere centre within this distance of the trap centre
    /// (inclusive), px.
    pub collision_radius_px: f64,
    /// Steps after which an episode is truncated.
    pub time_limit: u32,
    /// Reward components.
    pub rewards: RewardConfig,
    /// Resolution of the image observation.
    pub image: ImageConfig,
}

/// The four reward components of the paper, each of which can be switched off.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RewardConfig {
    /// Reward every step (time pressure).
    pub time: f64,
    /// Reward per px moved toward the target (negative when moving away).
    pub carry: f64,
    /// Reward on collision.
    pub collision: f64,
    /// Reward on reaching the target.
    pub success: f64,
    /// Components switched off (the paper's Fig. 4c ablation).
    pub off: Vec<RewardComponent>,
}

/// One of the paper's reward components.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RewardComponent {
    /// The per-step time reward.
    Time,
    /// The carry reward.
    Carry,
    /// The collision reward.
    Collision,
    /// The success reward.
    Success,
}

/// Resolution of the binary image the networks see.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ImageConfig {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl Default for EnvConfig {
    fn default() -> Self {
        Self {
            fov_px: [1280, 1024],
            world_px: [10240.0, 8192.0],
            sphere_diameter_px: 54.0,
            min_free_spheres: 500,
            max_free_spheres: 1000,
            brownian_accel_px: 0.5,
            max_sphere_speed_px: 2.0,
            start_clearance_px: 108.0,
            stage_speed_px: 10.0,
            target_distance_px: 1000.0,
            success_radius_px: 27.0,
            collision_radius_px: 54.0,
            time_limit: 1000,
            rewards: RewardConfig::default(),
            image: ImageConfig::default(),
        }
    }
}

impl Default for RewardConfig {
    fn default() -> Self {
        Self {
            time: -1.0,
            carry: 1.0,
            collision: -100.0,
            success: 1000.0,
            off: Vec::new(),
        }
    }
}

impl Default for ImageConfig {
    fn default() -> Self {
        Self {
            width: 320,
            height: 256,
        }
    }
}

fn positive(field: &str, value: f64) -> Result<(), ConfigError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(ConfigError::invalid(
            field,
            format!("must be a finite number > 0, got {value}"),
        ))
    }
}

fn finite(field: &str, value: f64) -> Result<(), ConfigError> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(ConfigError::invalid(
            field,
            format!("must be finite, got {value}"),
        ))
    }
}

impl EnvConfig {
    /// Parses and validates a TOML document.
    pub fn from_toml(text: &str) -> Result<Self, ConfigError> {
        let config: Self = toml::from_str(text).map_err(|e| ConfigError::Parse(e.to_string()))?;
        config.validate()?;
        Ok(config)
    }

    /// Reads, parses and validates a TOML file.
    pub fn from_file(path: &Path) -> Result<Self, ConfigError> {
        let config: Self = read_toml(path)?;
        config.validate()?;
        Ok(config)
    }

    /// Checks every field; the error names the first one out of range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.fov_px.contains(&0) {
            return Err(ConfigError::invalid("fov_px", "both sides must be > 0"));
        }
        positive("world_px", self.world_px[0])?;
        positive("world_px", self.world_px[1])?;
        if self.world_px[0] < f64::from(self.fov_px[0])
            || self.world_px[1] < f64::from(self.fov_px[1])
        {
            return Err(ConfigError::invalid(
                "world_px",
                "the world must be at least as large as the field of view",
            ));
        }
        positive("sphere_diameter_px", self.sphere_diameter_px)?;
        if self.min_free_spheres > self.max_free_spheres {
            return Err(ConfigError::invalid(
                "min_free_spheres",
                format!(
                    "{} is more than max_free_spheres = {}",
                    self.min_free_spheres, self.max_free_spheres
                ),
            ));
        }
        if self.max_free_spheres > 1_000_000 {
            return Err(ConfigError::invalid(
                "max_free_spheres",
                "must be at most 1,000,000",
            ));
        }
        finite("brownian_accel_px", self.brownian_accel_px)?;
        if self.brownian_accel_px < 0.0 {
            return Err(ConfigError::invalid("brownian_accel_px", "must be >= 0"));
        }
        finite("max_sphere_speed_px", self.max_sphere_speed_px)?;
        if self.max_sphere_speed_px < 0.0 {
            return Err(ConfigError::invalid("max_sphere_speed_px", "must be >= 0"));
        }
        if 2.0 * self.max_sphere_speed_px >= self.world_px[0].min(self.world_px[1]) {
            return Err(ConfigError::invalid(
                "max_sphere_speed_px",
                "must be less than half the world's smaller side",
            ));
        }
        finite("start_clearance_px", self.start_clearance_px)?;
        if self.start_clearance_px < 0.0 {
            return Err(ConfigError::invalid("start_clearance_px", "must be >= 0"));
        }
        let half_diagonal = 0.5 * self.world_px[0].hypot(self.world_px[1]);
        if self.start_clearance_px >= 0.5 * half_diagonal {
            return Err(ConfigError::invalid(
                "start_clearance_px",
                "leaves too little of the world to place free spheres in",
            ));
        }
        positive("stage_speed_px", self.stage_speed_px)?;
        positive("target_distance_px", self.target_distance_px)?;
        finite("success_radius_px", self.success_radius_px)?;
        if self.success_radius_px < 0.0 {
            return Err(ConfigError::invalid("success_radius_px", "must be >= 0"));
        }
        if self.success_radius_px >= self.target_distance_px {
            return Err(ConfigError::invalid(
                "success_radius_px",
                "must be smaller than target_distance_px, or every episode starts at the target",
            ));
        }
        finite("collision_radius_px", self.collision_radius_px)?;
        if self.collision_radius_px < 0.0 {
            return Err(ConfigError::invalid("collision_radius_px", "must be >= 0"));
        }
        if self.collision_radius_px >= self.start_clearance_px && self.start_clearance_px > 0.0 {
            return Err(ConfigError::invalid(
                "collision_radius_px",
                "must be smaller than start_clearance_px, or episodes can start in a collision",
            ));
        }
        // Collisions are scored among the spheres the camera can see.
        let visible = 0.5 * f64::from(self.fov_px[0].min(self.fov_px[1])) + self.sphere_radius_px();
        if self.collision_radius_px > visible {
            return Err(ConfigError::invalid(
                "collision_radius_px",
                format!("must be at most {visible} px, so that a collision happens in view"),
            ));
        }
        if self.time_limit == 0 {
            return Err(ConfigError::invalid(
                "time_limit",
                "must be at least 1 step",
            ));
        }
        if self.time_limit > 1_000_000 {
            return Err(ConfigError::invalid(
                "time_limit",
                "must be at most 1,000,000 steps",
            ));
        }
        finite("rewards.time", self.rewards.time)?;
        finite("rewards.carry", self.rewards.carry)?;
        finite("rewards.collision", self.rewards.collision)?;
        finite("rewards.success", self.rewards.success)?;
        // A mismatch is blamed on the field the user set: with the default
        // image, that is the field of view.
        self.image.validate(self.fov_px).map_err(|e| match e {
            ConfigError::Invalid { reason, .. } if self.image == ImageConfig::default() => {
                ConfigError::invalid("fov_px", format!("{reason} (the default [env.image])"))
            }
            other => other,
        })
    }

    /// Sphere radius in px.
    pub fn sphere_radius_px(&self) -> f64 {
        0.5 * self.sphere_diameter_px
    }

    /// The smallest and largest reward one step can earn: the time reward,
    /// the carry reward of a trap that moves at most `stage_speed_px` per
    /// axis, and the collision or success reward when they apply (each
    /// component only when switched on).
    pub fn reward_range(&self) -> [f64; 2] {
        let r = &self.rewards;
        let on = |component, lo: f64, hi: f64| {
            if self.reward_on(component) {
                [lo, hi]
            } else {
                [0.0, 0.0]
            }
        };
        let carry = r.carry.abs() * self.stage_speed_px * std::f64::consts::SQRT_2;
        [
            on(RewardComponent::Time, r.time, r.time),
            on(RewardComponent::Carry, -carry, carry),
            on(
                RewardComponent::Collision,
                r.collision.min(0.0),
                r.collision.max(0.0),
            ),
            on(
                RewardComponent::Success,
                r.success.min(0.0),
                r.success.max(0.0),
            ),
        ]
        .iter()
        .fold([0.0, 0.0], |[lo, hi], [a, b]| [lo + a, hi + b])
    }

    /// Whether a free sphere `offset` px from the trap's centre has
    /// entered the trap.
    pub fn collides(&self, offset: [f64; 2]) -> bool {
        let reach = self.collision_radius_px;
        offset[0] * offset[0] + offset[1] * offset[1] <= reach * reach
    }

    /// How an episode stands after its step number `steps`, with the trap
    /// `to_target` px from the target: a collision first, then success,
    /// then the time limit. The one rule for the virtual environment and
    /// the instrument.
    pub fn outcome(&self, collided: bool, to_target: f64, steps: u32) -> Outcome {
        if collided {
            Outcome::Collision
        } else if to_target <= self.success_radius_px {
            Outcome::Success
        } else if steps >= self.time_limit {
            Outcome::Timeout
        } else {
            Outcome::Running
        }
    }

    /// Whether a reward component is switched on.
    pub fn reward_on(&self, component: RewardComponent) -> bool {
        !self.rewards.off.contains(&component)
    }
}

impl ImageConfig {
    /// Checks the resolution against the field of view: both axes must be
    /// shrunk by the same factor, so that pixels stay square.
    pub fn validate(&self, fov_px: [u32; 2]) -> Result<(), ConfigError> {
        if self.width == 0 || self.height == 0 {
            return Err(ConfigError::invalid(
                "image",
                "width and height must be > 0",
            ));
        }
        if self.width > fov_px[0] || self.height > fov_px[1] {
            return Err(ConfigError::invalid(
                "image",
                format!(
                    "{}x{} is finer than the {}x{} px field of view",
                    self.width, self.height, fov_px[0], fov_px[1]
                ),
            ));
        }
        // Square pixels: width / height == fov width / fov height, exactly.
        if u64::from(self.width) * u64::from(fov_px[1])
            != u64::from(self.height) * u64::from(fov_px[0])
        {
            // The nearest fitting image of the same width, if there is one.
            let scaled = u64::from(self.width) * u64::from(fov_px[1]);
            let fitting = if scaled.is_multiple_of(u64::from(fov_px[0])) {
                format!(
                    " (such as {}x{})",
                    self.width,
                    scaled / u64::from(fov_px[0])
                )
            } else {
                String::new()
            };
            return Err(ConfigError::invalid(
                "image",
                format!(
                    "the image's {}x{} pixels and the {}x{} px field of view (fov_px) differ in aspect ratio, so pixels would not be square: give [env.image] width and height in the ratio {}:{}{fitting}",
                    self.width, self.height, fov_px[0], fov_px[1], fov_px[0], fov_px[1]
                ),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_spec() {
        let c = EnvConfig::default();
        c.validate().unwrap();
        assert_eq!(c.fov_px, [1280, 1024]);
        assert_eq!(c.image.width, 320);
        assert_eq!(c.image.height, 256);
        assert_eq!(c.sphere_radius_px(), 27.0);
        assert!(c.reward_on(RewardComponent::Carry));
    }

    #[test]
    fn empty_toml_gives_the_defaults() {
        assert_eq!(EnvConfig::from_toml("").unwrap(), EnvConfig::default());
    }

    #[test]
    fn toml_overrides_and_switches_rewards_off() {
        let c = EnvConfig::from_toml(
            "time_limit = 500\n[rewards]\noff = [\"carry\", \"time\"]\n[image]\nwidth = 80\nheight = 64\n",
        )
        .unwrap();
        assert_eq!(c.time_limit, 500);
        assert!(!c.reward_on(RewardComponent::Carry));
        assert!(!c.reward_on(RewardComponent::Time));
        assert!(c.reward_on(RewardComponent::Success));
        assert_eq!(c.image.width, 80);
    }

    fn field_of(err: ConfigError) -> String {
        match err {
            ConfigError::Invalid { field, .. } => field,
            other => panic!("expected a field error, got {other}"),
        }
    }

    #[test]
    fn errors_name_the_field() {
        let cases: [(&str, &str); 9] = [
            (
                "collision_radius_px = 600.0\nstart_clearance_px = 700.0",
                "collision_radius_px",
            ),
            (
                "min_free_spheres = 10\nmax_free_spheres = 5",
                "min_free_spheres",
            ),
            ("stage_speed_px = 0.0", "stage_speed_px"),
            ("sphere_diameter_px = -3.0", "sphere_diameter_px"),
            ("time_limit = 0", "time_limit"),
            ("[image]\nwidth = 300\nheight = 256", "image"),
            ("[image]\nwidth = 2560\nheight = 2048", "image"),
            ("success_radius_px = 2000.0", "success_radius_px"),
            ("world_px = [100.0, 100.0]", "world_px"),
        ];
        for (text, field) in cases {
            let err = EnvConfig::from_toml(text).unwrap_err();
            assert!(err.to_string().contains(field), "{err}");
            assert_eq!(field_of(err), field, "for {text:?}");
        }
    }

    #[test]
    fn file_errors_name_the_file_and_nested_fields_their_table() {
        let dir = std::env::temp_dir().join(format!("tweezer-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("bad.toml");
        std::fs::write(&path, "time_limit = 0\n").unwrap();
        let err = EnvConfig::from_file(&path).unwrap_err().in_table("env");
        assert_eq!(field_of(err), "env.time_limit");
        std::fs::write(&path, "time_limt = 3\n").unwrap();
        let err = EnvConfig::from_file(&path).unwrap_err().to_string();
        assert!(
            err.contains("bad.toml") && err.contains("time_limt"),
            "{err}"
        );
        let err = EnvConfig::from_file(&dir.join("missing.toml")).unwrap_err();
        assert!(matches!(err, ConfigError::Read { .. }));

        let config = EnvConfig {
            rewards: RewardConfig {
                off: vec![RewardComponent::Carry],
                ..RewardConfig::default()
            },
            ..EnvConfig::default()
        };
        std::fs::write(&path, toml::to_string(&config).unwrap()).unwrap();
        assert_eq!(EnvConfig::from_file(&path).unwrap(), config);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn non_finite_values_are_refused() {
        let c = EnvConfig {
            rewards: RewardConfig {
                success: f64::NAN,
                ..RewardConfig::default()
            },
            ..EnvConfig::default()
        };
        assert_eq!(field_of(c.validate().unwrap_err()), "rewards.success");
    }

    #[test]
    fn unknown_fields_and_bad_types_are_parse_errors() {
        let err = EnvConfig::from_toml("stage_sped_px = 3.0").unwrap_err();
        assert!(matches!(err, ConfigError::Parse(_)));
        assert!(err.to_string().contains("stage_sped_px"), "{err}");
        let err = EnvConfig::from_toml("[rewards]\noff = [\"speed\"]").unwrap_err();
        assert!(err.to_string().contains("speed"), "{err}");
    }
}
