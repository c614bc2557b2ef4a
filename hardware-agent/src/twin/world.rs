//! The twin's microscope: two simulated KDC101s on pseudo-terminals move a
//! virtual sample of free spheres (an episode of the virtual environment)
//! under the trap, and its camera renders what the objective would see.

use super::OpticsConfig;
use kdc101::{ActuatorModel, Calibration, ImageAxis, PtySimulator};
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;
use tweezer_config::{ConfigError, in_range};
use tweezer_gym::{Env, EnvConfig, SplitMix64};
use tweezer_vision::{Camera, CameraError, GrayFrame};

/// The `[twin]` table: the digital twin of the microscope.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TwinConfig {
    /// How its camera renders frames.
    pub optics: OpticsConfig,
    /// Reply latency of the simulated controllers, ms.
    pub latency_ms: u64,
    /// Lost motion on reversal of the simulated actuators, µm.
    pub backlash_um: f64,
    /// Where both actuators start, mm.
    pub start_mm: f64,
    /// How the twin's stages truly move its image, when that differs from
    /// what `[stages]` says (the calibration `calibrate --twin` must find).
    pub truth: Option<TrueCalibration>,
}

/// The `[twin.truth]` table: the twin's own calibration.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrueCalibration {
    /// Camera pixels per µm of stage travel.
    pub px_per_um: f64,
    /// Which stage moves the sample along the image's x axis.
    pub image_x: ImageAxis,
    /// Stage X's sign, as `stages.x_sign`.
    pub x_sign: f64,
    /// Stage Y's sign.
    pub y_sign: f64,
}

impl TrueCalibration {
    /// As the stage driver uses it.
    pub fn calibration(&self) -> Calibration {
        Calibration {
            px_per_um: self.px_per_um,
            image_x: self.image_x,
            signs: [self.x_sign, self.y_sign],
        }
    }
}

impl Default for TwinConfig {
    fn default() -> Self {
        Self {
            optics: OpticsConfig::default(),
            latency_ms: 2,
            backlash_um: 8.0,
            start_mm: 6.0,
            truth: None,
        }
    }
}

impl TwinConfig {
    /// Checks every field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.optics.validate().map_err(|e| e.in_table("optics"))?;
        if self.latency_ms > 1000 {
            return Err(ConfigError::invalid(
                "latency_ms",
                format!("{}: at most 1000", self.latency_ms),
            ));
        }
        if let Some(truth) = &self.truth {
            in_range("truth.px_per_um", truth.px_per_um, 0.01, 1000.0)?;
            for (name, sign) in [
                ("truth.x_sign", truth.x_sign),
                ("truth.y_sign", truth.y_sign),
            ] {
                if sign.abs() != 1.0 {
                    return Err(ConfigError::invalid(
                        name,
                        format!("{sign} must be 1 or -1"),
                    ));
                }
            }
        }
        for (name, value, lo, hi) in [
            ("backlash_um", self.backlash_um, 0.0, 100.0),
            ("start_mm", self.start_mm, 0.0, 12.0),
        ] {
            in_range(name, value, lo, hi)?;
        }
        Ok(())
    }
}

/// The twin's two stages (X, Y), each a simulated KDC101 on its own
/// pseudo-terminal.
#[derive(Debug)]
pub struct TwinStages([PtySimulator; 2]);

impl TwinStages {
    /// Starts both controllers.
    pub fn spawn(config: &TwinConfig) -> std::io::Result<Self> {
        let model = ActuatorModel {
            travel_mm: 12.0,
            backlash_mm: config.backlash_um / 1000.0,
            start_mm: config.start_mm,
            // As after `hardware-agent home`.
            homed: true,
        };
        let latency = Duration::from_millis(config.latency_ms);
        Ok(Self([
            PtySimulator::spawn(27_000_001, model, latency)?,
            PtySimulator::spawn(27_000_002, model, latency)?,
        ]))
    }

    /// The terminals to open as stage X's and stage Y's serial ports.
    pub fn ports(&self) -> [&Path; 2] {
        [self.0[0].path(), self.0[1].path()]
    }

    /// The stages themselves (X, Y).
    pub fn stages(&self) -> &[PtySimulator; 2] {
        &self.0
    }

    /// Where the carriages truly are (X, Y), mm.
    pub fn carriage_mm(&self) -> [f64; 2] {
        [0, 1].map(|k| self.0[k].controller().carriage_mm())
    }
}

/// The twin's camera: each grab advances the virtual sample one step with
/// the trap wherever the simulated carriages put it, and renders the frame.
#[derive(Debug)]
pub struct TwinCamera {
    stages: Arc<TwinStages>,
    env: Env,
    optics: OpticsConfig,
    calibration: Calibration,
    /// Carriage positions when the episode started.
    origin_mm: [f64; 2],
    collision_radius_px: f64,
    frames: u64,
    collided: bool,
}

impl TwinCamera {
    /// A camera over `stages`, whose sample follows `env` mapped through
    /// `calibration`; its frame (the optics' size) is centred in the
    /// environment's field of view, which may be wider.
    pub fn new(
        stages: Arc<TwinStages>,
        env: &EnvConfig,
        optics: OpticsConfig,
        calibration: Calibration,
    ) -> Result<Self, ConfigError> {
        let fov = env.fov_px.map(|v| v as usize);
        if optics.size_px[0] > fov[0] || optics.size_px[1] > fov[1] {
            return Err(ConfigError::Invalid {
                field: "twin.optics.size_px".into(),
                reason: format!(
                    "{:?} is larger than env.fov_px {:?}: the frame must lie within the field of view",
                    optics.size_px, env.fov_px
                ),
            });
        }
        // The agent, not the world, decides when an episode ends: allow it
        // the time limit and more.
        let world = EnvConfig {
            time_limit: env
                .time_limit
                .saturating_mul(2)
                .saturating_add(64)
                .min(1_000_000),
            ..env.clone()
        };
        let mut camera = Self {
            env: Env::new(world)?,
            collision_radius_px: env.collision_radius_px,
            origin_mm: stages.carriage_mm(),
            stages,
            optics,
            calibration,
            frames: 0,
            collided: false,
        };
        camera.start_episode(0);
        Ok(camera)
    }

    /// Lays out episode `seed`'s free spheres around the trap where it is
    /// now; returns the episode's target relative to the trap, px.
    pub fn start_episode(&mut self, seed: u64) -> [f64; 2] {
        self.env.reset(seed);
        self.origin_mm = self.stages.carriage_mm();
        self.collided = false;
        let (start, target) = (self.env.trap(), self.env.target());
        [target[0] - start[0], target[1] - start[1]]
    }

    /// Whether a free sphere has truly entered the trap region since the
    /// episode started (the ground truth the agent's detection is judged by).
    pub fn collided(&self) -> bool {
        self.collided
    }

    /// The trap's true position relative to its start, px.
    pub fn trap_offset_px(&self) -> [f64; 2] {
        self.calibration
            .px(self.stages.carriage_mm(), self.origin_mm)
    }
}

impl Camera for TwinCamera {
    fn size(&self) -> [usize; 2] {
        self.optics.size_px
    }

    fn grab(&mut self) -> Result<GrayFrame, CameraError> {
        let fov = self.env.config().fov_px.map(f64::from);
        let start = self.env.start_position();
        let offset = self.trap_offset_px();
        let trap = [start[0] + offset[0], start[1] + offset[1]];
        // Past the world's time limit the sample stops moving.
        let centres = match self.env.drive_to(trap) {
            Ok(observation) => &observation.centres,
            Err(_) => &self.env.observation().centres,
        };
        let trap_fov = [fov[0] / 2.0, fov[1] / 2.0];
        let [w, h] = self.optics.size_px.map(|v| v as f64);
        // The frame's origin in the field of view.
        let offset = [trap_fov[0] - w / 2.0, trap_fov[1] - h / 2.0];
        let reach = self.collision_radius_px;
        let mut spheres = Vec::with_capacity(centres.len() + 1);
        spheres.push([w / 2.0, h / 2.0]);
        for c in centres {
            let c = [f64::from(c[0]), f64::from(c[1])];
            if (c[0] - trap_fov[0]).hypot(c[1] - trap_fov[1]) <= reach {
                self.collided = true;
            }
            spheres.push([c[0] - offset[0], c[1] - offset[1]]);
        }
        self.frames += 1;
        let seed = SplitMix64::derived(self.env.seed(), self.frames).next_u64();
        let debris = self.optics.debris(&mut SplitMix64::new(seed));
        Ok(self.optics.render(&spheres, &debris, seed))
    }
}
