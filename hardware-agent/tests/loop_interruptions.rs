//! The control loop interrupted in the middle of a step, by a camera
//! injected into the digital twin's rig that misbehaves on one grab:
//! - it stalls past the period plus the deadline margin: the watchdog stops
//!   the stages and the episode ends as a fault (the watchdog's deadline,
//!   the step's start plus the period and the margin, is also the next
//!   step's latest start, so a step that would start beyond its margin
//!   finds the watchdog already tripped);
//! - an emergency stop arrives, as the service sends it: the episode ends
//!   emergency-stopped.
//!
//! Either way the interrupted step sends no more commands: the stages stay
//! stopped.

use kdc101::{StagePair, Stopper};
use serialport::TTYPort;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tweezer_gym::{EnvConfig, Greedy};
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_hardware_agent::control::{ControlConfig, Ending, Halt, HaltKind, Rig};
use tweezer_hardware_agent::overlay::Overlay;
use tweezer_hardware_agent::twin::{TwinCamera, TwinStages};
use tweezer_vision::{Camera, CameraError, GrayFrame, Segmenter};

/// The grab on which the camera misbehaves (grab 6 is step 5).
const BAD_GRAB: u32 = 6;

/// What the camera does on grab [`BAD_GRAB`].
enum Mischief {
    /// Sleeps this long.
    Stall(Duration),
    /// Sends an emergency stop as the service does: the request, then the
    /// stop.
    EmergencyStop(Halt, Stopper<TTYPort>),
}

/// A camera that misbehaves once and notes how fast the stages were moving
/// right after.
struct Interrupting {
    inner: TwinCamera,
    stages: Arc<TwinStages>,
    mischief: Mischief,
    grabs: u32,
    /// The stages' speeds (X, Y) right after the mischief, mm/s.
    after: Option<[f64; 2]>,
}

impl Camera for Interrupting {
    fn size(&self) -> [usize; 2] {
        self.inner.size()
    }

    fn grab(&mut self) -> Result<GrayFrame, CameraError> {
        self.grabs += 1;
        if self.grabs == BAD_GRAB {
            match &self.mischief {
                Mischief::Stall(stall) => std::thread::sleep(*stall),
                Mischief::EmergencyStop(halt, stopper) => {
                    halt.request(HaltKind::Emergency("test".into()));
                    stopper.stop_now().unwrap();
                    until_still(&self.stages);
                }
            }
            self.after = Some(speeds(&self.stages));
        }
        self.inner.grab()
    }
}

fn speeds(stages: &TwinStages) -> [f64; 2] {
    [0, 1].map(|k| stages.stages()[k].controller().speed_mm_s())
}

/// What an interrupted episode did.
struct Interrupted {
    ending: Ending,
    /// Steps completed.
    steps: u32,
    /// The last step that commanded the stages.
    last_logged: Option<u32>,
    /// The stages' speeds right after the mischief, mm/s.
    after: Option<[f64; 2]>,
    twin: Arc<TwinStages>,
}

/// The twin without free spheres (nothing else ends an episode early), a
/// loop at 10 Hz with a 300 ms deadline margin (wide enough that a loaded
/// test machine does not end the episode before the mischief), and a
/// camera that does what `mischief` says with the episode's halt and the
/// stages' stopper; runs greedy episode 1 on it.
fn interrupted_episode(mischief: impl FnOnce(&Halt, Stopper<TTYPort>) -> Mischief) -> Interrupted {
    let config = AgentConfig {
        env: EnvConfig {
            min_free_spheres: 0,
            max_free_spheres: 0,
            ..EnvConfig::default()
        },
        ..AgentConfig::default()
    };
    let control = ControlConfig {
        rate_hz: 10.0,
        deadline_margin_ms: 300.0,
        ..config.control.clone()
    };
    let twin = Arc::new(TwinStages::spawn(&config.twin).unwrap());
    let (stages, _) =
        StagePair::<TTYPort>::open_paths(twin.ports(), &config.stages, control.command_interval())
            .unwrap();
    let mut camera = TwinCamera::new(
        twin.clone(),
        &config.env,
        config.twin.optics.clone(),
        config.stages.calibration(),
    )
    .unwrap();
    let target = camera.start_episode(1);
    let halt = Halt::default();
    let camera = Interrupting {
        inner: camera,
        stages: twin.clone(),
        mischief: mischief(&halt, stages.stopper()),
        grabs: 0,
        after: None,
    };
    let segmenter = Segmenter::new(config.segmentation.clone(), camera.size()).unwrap();
    let mut rig = Rig::new(
        camera,
        stages,
        segmenter,
        config.env.clone(),
        control,
        Overlay::default(),
    )
    .unwrap();
    let mut last_logged = None;
    let summary = rig.run_episode(&mut Greedy, target, &halt, |log| {
        last_logged = Some(log.step);
    });
    Interrupted {
        ending: summary.ending,
        steps: summary.steps,
        last_logged,
        after: rig.camera().after,
        twin,
    }
}

/// Waits (at most 2 s) for both stages to stand still.
fn until_still(twin: &TwinStages) {
    let start = Instant::now();
    while speeds(twin) != [0.0; 2] {
        assert!(
            start.elapsed() < Duration::from_secs(2),
            "the stages kept moving: {:?} mm/s",
            speeds(twin)
        );
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// Checks that the episode ended at the bad step without commanding the
/// stages again, and that they stand still.
fn ended_at_the_bad_step(interrupted: &Interrupted) {
    let bad_step = BAD_GRAB - 1;
    let ending = &interrupted.ending;
    assert_eq!(interrupted.steps, bad_step, "{ending:?}");
    assert_eq!(interrupted.last_logged, Some(bad_step - 1), "{ending:?}");
    // Stopped by the time the camera returned.
    assert_eq!(interrupted.after, Some([0.0; 2]), "{ending:?}");
    until_still(&interrupted.twin);
}

#[test]
fn a_stall_past_the_watchdog_stops_the_stages_and_they_stay_stopped() {
    // 1.2 s: three times what the watchdog allows (period + margin).
    let interrupted = interrupted_episode(|_, _| Mischief::Stall(Duration::from_millis(1200)));
    let Ending::Fault(reason) = &interrupted.ending else {
        panic!(
            "a stalled loop must end the episode as a fault, not {:?}",
            interrupted.ending
        )
    };
    assert!(reason.contains("watchdog"), "{reason}");
    ended_at_the_bad_step(&interrupted);
}

#[test]
fn an_emergency_stop_in_mid_step_is_not_undone_by_that_step() {
    let interrupted =
        interrupted_episode(|halt, stopper| Mischief::EmergencyStop(halt.clone(), stopper));
    assert_eq!(interrupted.ending, Ending::EmergencyStopped("test".into()));
    ended_at_the_bad_step(&interrupted);
}
