//! The instrument as the loop drives it: camera, segmentation, stages,
//! overlay and watchdog, and the episode loop over them.

use super::{ControlConfig, Ending, EpisodeSummary, Halt, HaltKind, LoopTiming, StepLog, Watchdog};
use crate::overlay::Overlay;
use kdc101::apt::StopMode;
use kdc101::{StagePair, Stopper};
use std::io::{Read, Write};
use std::time::{Duration, Instant};
use tweezer_gym::{
    Action, EnvConfig, Observation, ObservationBounds, Outcome, Policy, SphereTracker,
};
use tweezer_vision::Camera;
use tweezer_vision::{Detection, SegmentError, Segmenter};

/// A rig that cannot be assembled.
#[derive(Debug, thiserror::Error)]
pub enum RigError {
    /// The camera's frames are larger than the environment's field of view.
    #[error(
        "the camera gives {camera:?} px frames, larger than env.fov_px {fov:?} (the policy's field of view holds the camera's, and virtual obstacles may fill a wider one)"
    )]
    FrameSize {
        /// The camera's frame size.
        camera: [usize; 2],
        /// The policy's field of view.
        fov: [u32; 2],
    },
    /// Bad segmentation settings.
    #[error(transparent)]
    Segment(#[from] SegmentError),
    /// A bad `[control]` table.
    #[error("{0}")]
    Control(String),
    /// The watchdog thread could not start.
    #[error("cannot start the watchdog: {0}")]
    Watchdog(std::io::Error),
}

/// Camera, stages and everything between them.
#[derive(Debug)]
pub struct Rig<C, P: Read + Write> {
    camera: C,
    stages: StagePair<P>,
    segmenter: Segmenter,
    env: EnvConfig,
    control: ControlConfig,
    overlay: Overlay,
    watchdog: Watchdog,
    bounds: ObservationBounds,
    /// Where the camera frame's origin lies in the policy's field of view.
    frame_offset: [f64; 2],
}

impl<C: Camera, P: Read + Write + Send + 'static> Rig<C, P> {
    /// Assembles a rig. The camera's frame lies centred in the policy's
    /// field of view (`env.fov_px`), which may be wider: virtual obstacles
    /// are known everywhere, so they fill what the camera cannot see.
    pub fn new(
        camera: C,
        stages: StagePair<P>,
        segmenter: Segmenter,
        env: EnvConfig,
        control: ControlConfig,
        overlay: Overlay,
    ) -> Result<Self, RigError> {
        control
            .validate()
            .map_err(|e| RigError::Control(e.in_table("control").to_string()))?;
        let fov = env.fov_px;
        let frame = camera.size();
        if frame[0] > fov[0] as usize || frame[1] > fov[1] as usize {
            return Err(RigError::FrameSize { camera: frame, fov });
        }
        let frame_offset = [0, 1].map(|a| 0.5 * (f64::from(fov[a]) - frame[a] as f64));
        let watchdog = Watchdog::spawn(stages.stopper()).map_err(RigError::Watchdog)?;
        Ok(Self {
            camera,
            bounds: ObservationBounds::for_config(&env),
            frame_offset,
            stages,
            segmenter,
            env,
            control,
            overlay,
            watchdog,
        })
    }

    /// The camera.
    pub fn camera(&mut self) -> &mut C {
        &mut self.camera
    }

    /// The stages.
    pub fn stages(&mut self) -> &mut StagePair<P> {
        &mut self.stages
    }

    /// Stops both motors from any thread.
    pub fn stopper(&self) -> Stopper<P> {
        self.stages.stopper()
    }

    /// The virtual obstacles.
    pub fn overlay(&self) -> &Overlay {
        &self.overlay
    }

    /// Replaces the virtual obstacles (between episodes).
    pub fn set_overlay(&mut self, overlay: Overlay) {
        self.overlay = overlay;
    }

    /// Runs one episode toward `target_offset_px` (image axes, from the
    /// trap's position now) with `policy`, until it ends or `halt` asks;
    /// `on_step` sees every step. The stages are stopped when it returns.
    pub fn run_episode(
        &mut self,
        policy: &mut dyn Policy,
        target_offset_px: [f64; 2],
        halt: &Halt,
        mut on_step: impl FnMut(&StepLog),
    ) -> EpisodeSummary {
        let started = Instant::now();
        let mut progress = Progress::default();
        let ready = self
            .camera
            .start()
            .map_err(|e| Ending::Fault(format!("camera: {e}")))
            .and_then(|()| {
                self.stages
                    .position_px()
                    .map_err(|e| Ending::Fault(e.to_string()))
            });
        let ending = match ready {
            Ok(start_px) => {
                progress.start_px = start_px;
                progress.end_px = start_px;
                progress.target_px = [
                    start_px[0] + target_offset_px[0],
                    start_px[1] + target_offset_px[1],
                ];
                self.drive(policy, halt, &mut on_step, &mut progress)
            }
            Err(ending) => ending,
        };
        self.watchdog.disarm();
        let _ = self.watchdog.take_tripped();
        let mode = match ending {
            Ending::Success | Ending::Stopped | Ending::Timeout => StopMode::Profiled,
            _ => StopMode::Immediate,
        };
        if self.stages.stop(mode).is_err() {
            // Whatever failed, the motors get the stop by the other path too.
            let _ = self.stages.stopper().stop_now();
        }
        self.camera.stop();
        let duration_s = started.elapsed().as_secs_f64();
        EpisodeSummary {
            timing: LoopTiming::of(&mut progress.latencies, duration_s, progress.steps),
            ending,
            steps: progress.steps,
            duration_s,
            start_px: progress.start_px,
            target_px: progress.target_px,
            end_px: progress.end_px,
        }
    }

    /// The episode's steps, each: wait for its tick, sense (frame,
    /// spheres, stage position), observe, score, act and command, log.
    fn drive(
        &mut self,
        policy: &mut dyn Policy,
        halt: &Halt,
        on_step: &mut impl FnMut(&StepLog),
        progress: &mut Progress,
    ) -> Ending {
        let (start_px, target_px) = (progress.start_px, progress.target_px);
        let period = Duration::from_secs_f64(self.control.period_s());
        let speed = self.control.px_per_step * self.control.rate_hz;
        let initial = (target_px[0] - start_px[0])
            .hypot(target_px[1] - start_px[1])
            .max(f64::MIN_POSITIVE);
        let started = Instant::now();
        let mut next = started;
        let mut lost = 0;
        let mut observation = Observation::default();
        let mut tracker = SphereTracker::for_config(&self.env);
        let mut action = [Action::ZERO];
        loop {
            // One step; `?` ends the episode with the step's ending.
            let step = (|| {
                let tick = self.wait_for_tick(halt, next, progress.steps)?;
                let sensed = self.sense()?;
                progress.end_px = sensed.position;
                let trapped = self.observe(&sensed, &mut tracker, &mut observation);
                let remaining = [0, 1].map(|a| target_px[a] - sensed.position[a]);
                if progress.steps > 0 {
                    self.score(&observation, trapped.is_some(), remaining, progress.steps)?;
                }
                let Some(trapped) = trapped else {
                    lost += 1;
                    if lost >= self.control.lost_trap_frames {
                        return Err(Ending::TrapLost);
                    }
                    return self.command(halt, [0.0; 2]);
                };
                lost = 0;
                observation.vector = goal_vector(remaining, initial);
                (observation.validate(&self.bounds))
                    .map_err(|e| Ending::Fault(format!("observation: {e}")))?;
                let thinking = Instant::now();
                policy.act(&[&observation], &mut action);
                let policy_ms = thinking.elapsed().as_secs_f64() * 1000.0;
                let [ax, ay] = action[0].components();
                self.command(halt, [f64::from(ax) * speed, f64::from(ay) * speed])?;
                let latency_ms = sensed.frame_in.elapsed().as_secs_f64() * 1000.0;
                progress.latencies.push(latency_ms);
                on_step(&StepLog {
                    step: progress.steps,
                    time_s: (tick - started).as_secs_f64(),
                    centres: observation.centres.clone(),
                    displacements: observation.displacements.clone(),
                    detected: sensed.detections.len() - 1,
                    trapped: sensed.detections[trapped].centre.map(|v| v as f32),
                    vector: observation.vector,
                    action: [ax, ay],
                    position_px: sensed.position,
                    stage_mm: sensed.stage_mm,
                    latency_ms,
                    policy_ms,
                });
                progress.steps += 1;
                Ok(())
            })();
            if let Err(ending) = step {
                return ending;
            }
            next += period;
        }
    }

    /// Waits for the tick due at `next`, then arms the watchdog for the
    /// step; the episode ends if a halt came or the tick is later than the
    /// margin allows.
    fn wait_for_tick(&self, halt: &Halt, next: Instant, step: u32) -> Result<Instant, Ending> {
        let period = Duration::from_secs_f64(self.control.period_s());
        let margin = Duration::from_secs_f64(self.control.deadline_margin_ms / 1000.0);
        halt.wait_until(next);
        let tick = Instant::now();
        if let Some(ending) = self.interrupted(halt) {
            return Err(ending);
        }
        if tick > next + margin {
            return Err(Ending::Fault(format!(
                "step {step} started {:.0} ms late, beyond the {:.0} ms margin",
                (tick - next).as_secs_f64() * 1000.0,
                margin.as_secs_f64() * 1000.0
            )));
        }
        self.watchdog.arm(tick + period + margin);
        Ok(tick)
    }

    /// A frame, the spheres in it (in the policy's field of view) and the
    /// stages' position.
    fn sense(&mut self) -> Result<Sensed, Ending> {
        let frame = (self.camera.grab()).map_err(|e| Ending::Fault(format!("camera: {e}")))?;
        let frame_in = self.camera.captured().unwrap_or_else(Instant::now);
        let mut detections = (self.segmenter.segment(&frame))
            .map_err(|e| Ending::Fault(format!("segmentation: {e}")))?;
        for d in &mut detections {
            d.centre = [0, 1].map(|a| d.centre[a] + self.frame_offset[a]);
        }
        let stage_mm = (self.stages.position_mm()).map_err(|e| Ending::Fault(e.to_string()))?;
        Ok(Sensed {
            frame_in,
            detections,
            position: self.stages.px(stage_mm),
            stage_mm,
        })
    }

    /// Fills `observation` with the free spheres the camera sees and the
    /// overlay's, tracked from the previous step; returns which detection
    /// is the trapped sphere, if one is.
    fn observe(
        &self,
        sensed: &Sensed,
        tracker: &mut SphereTracker,
        observation: &mut Observation,
    ) -> Option<usize> {
        let [fw, fh] = self.env.fov_px.map(f64::from);
        let centre = [fw / 2.0, fh / 2.0];
        let trapped = trapped_sphere(&sensed.detections, centre, self.control.trap_search_px);
        observation.centres.clear();
        observation.centres.extend(
            (sensed.detections.iter().enumerate())
                .filter(|&(k, _)| Some(k) != trapped)
                .map(|(_, d)| d.centre.map(|v| v as f32)),
        );
        let radius = self.env.sphere_radius_px();
        (self.overlay).visible(sensed.position, [fw, fh], radius, &mut observation.centres);
        tracker.track(
            &observation.centres,
            sensed.position,
            &mut observation.displacements,
        );
        trapped
    }

    /// Scores the step by the virtual environment's rule: the episode ends
    /// on a collision (with a free sphere or a virtual obstacle, which
    /// needs the trapped sphere in view), success or the time limit.
    fn score(
        &self,
        observation: &Observation,
        trap_seen: bool,
        remaining: [f64; 2],
        steps: u32,
    ) -> Result<(), Ending> {
        let [fw, fh] = self.env.fov_px.map(f64::from);
        let hit = observation
            .centres
            .iter()
            .any(|c| (self.env).collides([f64::from(c[0]) - fw / 2.0, f64::from(c[1]) - fh / 2.0]));
        let to_target = remaining[0].hypot(remaining[1]);
        match self.env.outcome(hit && trap_seen, to_target, steps) {
            Outcome::Collision => Err(Ending::Collision),
            Outcome::Success => Err(Ending::Success),
            Outcome::Timeout => Err(Ending::Timeout),
            Outcome::Running => Ok(()),
        }
    }

    /// Commands the stages to `velocity` px/s, unless a stop came. A stall
    /// in this step may have tripped the watchdog, or a stop come: then the
    /// stages stay as they were stopped. Checked again after the command:
    /// whoever stops records the request before stopping, so a request
    /// this second check misses is followed by its own stop, after the
    /// command.
    fn command(&mut self, halt: &Halt, velocity: [f64; 2]) -> Result<(), Ending> {
        if let Some(ending) = self.interrupted(halt) {
            return Err(ending);
        }
        (self.stages.set_velocity_px(velocity)).map_err(|e| Ending::Fault(e.to_string()))?;
        match self.interrupted(halt) {
            Some(ending) => Err(ending),
            None => Ok(()),
        }
    }
}

/// What a step sensed.
struct Sensed {
    /// When the frame reached the PC.
    frame_in: Instant,
    /// The spheres in the frame, in the policy's field of view.
    detections: Vec<Detection>,
    /// The stages' position, px and mm.
    position: [f64; 2],
    stage_mm: [f64; 2],
}

/// The target vector the policy sees: `remaining` over the episode's
/// `initial` distance, at most 1 long.
fn goal_vector(remaining: [f64; 2], initial: f64) -> [f32; 2] {
    let mut vector = remaining.map(|v| v / initial);
    let magnitude = vector[0].hypot(vector[1]);
    if magnitude > 1.0 {
        vector = vector.map(|v| v / magnitude);
    }
    vector.map(|v| v as f32)
}

impl<C, P: Read + Write> Rig<C, P> {
    /// How the episode ends if a halt was requested (an emergency stop
    /// outranks the rest) or the watchdog has tripped.
    fn interrupted(&self, halt: &Halt) -> Option<Ending> {
        match halt.pending() {
            Some(HaltKind::Emergency(reason)) => Some(Ending::EmergencyStopped(reason)),
            Some(HaltKind::Stop) => Some(Ending::Stopped),
            None => self
                .watchdog
                .take_tripped()
                .then(|| Ending::Fault("the watchdog stopped the stages: the loop stalled".into())),
        }
    }
}

/// Where an episode has got to.
#[derive(Debug, Default)]
struct Progress {
    start_px: [f64; 2],
    target_px: [f64; 2],
    end_px: [f64; 2],
    steps: u32,
    latencies: Vec<f64>,
}

/// The detection nearest `centre` within `search` px: the trapped sphere.
fn trapped_sphere(detections: &[Detection], centre: [f64; 2], search: f64) -> Option<usize> {
    detections
        .iter()
        .enumerate()
        .map(|(k, d)| (k, (d.centre[0] - centre[0]).hypot(d.centre[1] - centre[1])))
        .filter(|&(_, r)| r <= search)
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(k, _)| k)
}
