//! The instrument assembled from the configuration: the real stages and the
//! configured camera, or the digital twin's stages and camera, in a rig
//! with the overlay; and one recorded episode on it.

use crate::config::AgentConfig;
use crate::config::CameraSource;
use crate::control::{EpisodeSummary, Halt, Rig, StepLog};
use crate::overlay::{Overlay, OverlaySpec};
use crate::policy_source::LoadedPolicy;
use crate::record::{EpisodeHeader, EpisodeRecorder, RecordFiles};
use crate::twin::{TwinCamera, TwinStages};
use kdc101::StagePair;
use serde::Serialize;
use serialport::TTYPort;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;
use tweezer_vision::Segmenter;
use tweezer_vision::frame_stream::StreamCamera;
use tweezer_vision::{Camera, CameraError, FrameCounters, GrayFrame, ReplayCamera};

/// The camera an instrument was built with.
#[derive(Debug)]
pub enum InstrumentCamera {
    /// Frames replayed from a directory.
    Replay(ReplayCamera),
    /// The digital twin's camera.
    Twin(Box<TwinCamera>),
    /// A GenICam camera through Aravis.
    #[cfg(feature = "aravis")]
    Genicam(Box<tweezer_vision::genicam::GenicamCamera>),
    /// Frames another program writes.
    Stream(Box<StreamCamera>),
}

impl InstrumentCamera {
    fn inner(&mut self) -> &mut dyn Camera {
        match self {
            Self::Replay(c) => c,
            Self::Twin(c) => c.as_mut(),
            #[cfg(feature = "aravis")]
            Self::Genicam(c) => c.as_mut(),
            Self::Stream(c) => c.as_mut(),
        }
    }

    fn inner_ref(&self) -> &dyn Camera {
        match self {
            Self::Replay(c) => c,
            Self::Twin(c) => c.as_ref(),
            #[cfg(feature = "aravis")]
            Self::Genicam(c) => c.as_ref(),
            Self::Stream(c) => c.as_ref(),
        }
    }

    /// Opens the camera `config` describes (not the twin's), counting its
    /// frames in `counters`; a live camera waits at most `timeout` for a
    /// frame.
    fn open(
        config: &AgentConfig,
        timeout: std::time::Duration,
        counters: &Arc<FrameCounters>,
    ) -> Result<Self, InstrumentError> {
        match config.camera.source {
            CameraSource::Replay => Ok(Self::Replay(
                ReplayCamera::open(&config.camera.dir, config.camera.looping)
                    .map_err(|e| fail("camera")(&e))?,
            )),
            CameraSource::Stream => Ok(Self::Stream(Box::new(
                StreamCamera::open(&config.camera.stream, timeout, counters.clone())
                    .map_err(|e| fail("camera")(&e))?,
            ))),
            CameraSource::Twin => Err(InstrumentError(
                "camera.source = \"twin\" needs the twin's stages too: run with --twin".into(),
            )),
            #[cfg(feature = "aravis")]
            CameraSource::Genicam => {
                let camera = tweezer_vision::genicam::GenicamCamera::open(
                    &config.camera.genicam,
                    timeout,
                    counters.clone(),
                )
                .map_err(|e| fail("camera")(&e))?;
                tracing::info!(settings = ?camera.settings(), "GenICam camera connected");
                Ok(Self::Genicam(Box::new(camera)))
            }
            #[cfg(not(feature = "aravis"))]
            CameraSource::Genicam => Err(InstrumentError(format!(
                "camera.source = \"genicam\": {}",
                tweezer_vision::genicam::REBUILD_HINT
            ))),
        }
    }
}

impl Camera for InstrumentCamera {
    fn size(&self) -> [usize; 2] {
        self.inner_ref().size()
    }

    fn grab(&mut self) -> Result<GrayFrame, CameraError> {
        self.inner().grab()
    }

    fn captured(&self) -> Option<Instant> {
        self.inner_ref().captured()
    }

    fn start(&mut self) -> Result<(), CameraError> {
        self.inner().start()
    }

    fn stop(&mut self) {
        self.inner().stop();
    }
}

/// What truly happened in a twin episode, to judge the agent's view by.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct TwinTruth {
    /// A free sphere entered the trap region.
    pub collided: bool,
    /// The trap truly ended within the success radius of the target.
    pub reached: bool,
    /// Distance between the trap's true end position and the agent's
    /// estimate from the stage positions, px.
    pub position_error_px: f64,
}

/// An instrument that cannot be assembled.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct InstrumentError(String);

fn fail(what: &str) -> impl Fn(&dyn std::fmt::Display) -> InstrumentError + '_ {
    move |e| InstrumentError(format!("{what}: {e}"))
}

/// Stages, camera and loop, ready for episodes.
#[derive(Debug)]
pub struct Instrument {
    rig: Rig<InstrumentCamera, TTYPort>,
    /// The twin's stages, when this is the twin (they live as long as the
    /// instrument).
    twin: Option<Arc<TwinStages>>,
    /// What the camera delivered and refused.
    counters: Arc<FrameCounters>,
    config: AgentConfig,
}

impl Instrument {
    /// Connects to the configured stages and camera, or with `twin` to a
    /// freshly started digital twin.
    pub fn open(config: &AgentConfig, twin: bool) -> Result<Self, InstrumentError> {
        let command_interval = config.control.command_interval();
        let counters = Arc::new(FrameCounters::default());
        if twin && config.camera.source != CameraSource::Twin {
            return Err(InstrumentError(format!(
                "camera.source = \"{}\" conflicts with --twin, which renders the twin's own frames: drop --twin to use that camera, or set camera.source = \"twin\"",
                config.camera.source.name()
            )));
        }
        let (stages, camera, twin) = if twin {
            let twin = Arc::new(
                TwinStages::spawn(&config.twin).map_err(|e| fail("cannot start the twin")(&e))?,
            );
            let [x, y] = twin.ports();
            // Other APT software can be pointed at these.
            tracing::info!(
                x_port = %x.display(),
                y_port = %y.display(),
                "the twin's simulated KDC101 controllers are on these pseudo-terminals"
            );
            let (stages, _) = StagePair::open_paths(twin.ports(), &config.stages, command_interval)
                .map_err(|e| fail("twin stages")(&e))?;
            let truth = config.twin.truth.as_ref();
            let camera = TwinCamera::new(
                twin.clone(),
                &config.env,
                config.twin.optics.clone(),
                truth.map_or_else(|| config.stages.calibration(), |t| t.calibration()),
            )
            .map_err(|e| fail("twin camera")(&e))?;
            (stages, InstrumentCamera::Twin(Box::new(camera)), Some(twin))
        } else {
            // A step waits at most a control period for its frame.
            let timeout = std::time::Duration::from_secs_f64(config.control.period_s());
            let camera = InstrumentCamera::open(config, timeout, &counters)?;
            let (stages, _) = StagePair::open(&config.stages, command_interval)
                .map_err(|e| fail("stages")(&e))?;
            (stages, camera, None)
        };
        let overlay = Self::overlay(config, stages.travel_px())?;
        let segmenter = Segmenter::new(config.segmentation.clone(), camera.size())
            .map_err(|e| fail("segmentation")(&e))?;
        let rig = Rig::new(
            camera,
            stages,
            segmenter,
            config.env.clone(),
            config.control.clone(),
            overlay,
        )
        .map_err(|e| fail("rig")(&e))?;
        Ok(Self {
            rig,
            twin,
            counters,
            config: config.clone(),
        })
    }

    /// The configured overlay file's obstacles and the keep-out walls.
    fn overlay(config: &AgentConfig, travel: [[f64; 2]; 2]) -> Result<Overlay, InstrumentError> {
        let spec = match &config.overlay.file {
            Some(path) => OverlaySpec::from_file(path).map_err(|e| fail("overlay")(&e))?,
            None => OverlaySpec::default(),
        };
        Self::build_overlay(config, &spec, travel)
    }

    fn build_overlay(
        config: &AgentConfig,
        spec: &OverlaySpec,
        travel: [[f64; 2]; 2],
    ) -> Result<Overlay, InstrumentError> {
        let px_per_um = config.stages.px_per_um;
        let overlay = Overlay::new(spec, px_per_um, config.env.sphere_radius_px())
            .map_err(|e| fail("overlay")(&e))?;
        Ok(if config.overlay.keep_out_um > 0.0 {
            overlay.with_keep_out(travel, config.overlay.keep_out_um * px_per_um)
        } else {
            overlay
        })
    }

    /// Replaces the virtual obstacles (between episodes).
    pub fn set_overlay(&mut self, spec: &OverlaySpec) -> Result<(), InstrumentError> {
        let travel = self.rig.stages().travel_px();
        let overlay = Self::build_overlay(&self.config, spec, travel)?;
        self.rig.set_overlay(overlay);
        Ok(())
    }

    /// Virtual obstacle discs in the overlay (keep-out walls aside).
    pub fn overlay_len(&self) -> usize {
        self.rig.overlay().discs().len()
    }

    /// The camera's frame counters, for the metrics.
    pub fn frame_counters(&self) -> Arc<FrameCounters> {
        self.counters.clone()
    }

    /// The rig.
    pub fn rig(&mut self) -> &mut Rig<InstrumentCamera, TTYPort> {
        &mut self.rig
    }

    /// The twin's stages, if this is the twin.
    pub fn twin(&self) -> Option<&Arc<TwinStages>> {
        self.twin.as_ref()
    }

    /// Lays out twin episode `seed` around the trap; its target relative to
    /// the trap, px (`None` unless this is the twin).
    pub fn start_twin_episode(&mut self, seed: u64) -> Option<[f64; 2]> {
        match self.rig.camera() {
            InstrumentCamera::Twin(camera) => Some(camera.start_episode(seed)),
            _ => None,
        }
    }

    /// What truly happened in the twin's episode that `summary` describes
    /// (`None` unless this is the twin).
    pub fn twin_truth(&mut self, summary: &EpisodeSummary) -> Option<TwinTruth> {
        let InstrumentCamera::Twin(camera) = self.rig.camera() else {
            return None;
        };
        let offset = camera.trap_offset_px();
        let estimate = [
            summary.end_px[0] - summary.start_px[0],
            summary.end_px[1] - summary.start_px[1],
        ];
        let to_target = [
            summary.target_px[0] - summary.start_px[0] - offset[0],
            summary.target_px[1] - summary.start_px[1] - offset[1],
        ];
        Some(TwinTruth {
            collided: camera.collided(),
            reached: to_target[0].hypot(to_target[1]) <= self.config.env.success_radius_px,
            position_error_px: (offset[0] - estimate[0]).hypot(offset[1] - estimate[1]),
        })
    }

    /// Runs and records one episode toward `header.target_offset_px`.
    pub fn run_recorded(
        &mut self,
        policy: &mut LoadedPolicy,
        header: &EpisodeHeader,
        records: &Path,
        halt: &Halt,
        mut on_step: impl FnMut(&StepLog),
    ) -> Result<(EpisodeSummary, RecordFiles), InstrumentError> {
        let fov = self.config.env.fov_px.map(f64::from);
        let radius = self.config.env.sphere_radius_px();
        let mut recorder = EpisodeRecorder::create(records, header, fov, radius)
            .map_err(|e| fail("records")(&e))?;
        let summary = self.rig.run_episode(
            policy.policy.as_mut(),
            header.target_offset_px,
            halt,
            |log| {
                recorder.step(log);
                on_step(log);
            },
        );
        let files = recorder
            .finish(&summary, self.rig.overlay().discs())
            .map_err(|e| fail("records")(&e))?;
        Ok((summary, files))
    }
}
