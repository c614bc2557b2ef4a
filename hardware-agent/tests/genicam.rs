//! GenICam cameras through Aravis, against Aravis's own simulated GigE
//! Vision camera (`arv-fake-gv-camera-0.8`, Debian's aravis-tools) on
//! loopback, where it is reached by address: discovery by address, the
//! settings read back, a feature refused, frames at the configured rate,
//! software triggering, incomplete frames counted, the time from a frame
//! to its command measured (`bench --camera`), and the camera killed
//! mid-episode (a fault with the stages stopped, then a reconnect). The simulated camera serves its own
//! test pattern, not spheres: segmentation is tested on the twin's frames
//! (`segmentation.rs`). Built with `--features aravis` only.
#![cfg(feature = "aravis")]

mod common;

use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tweezer_gym::Baseline;
use tweezer_hardware_agent::control::{ControlConfig, Ending, Halt};
use tweezer_hardware_agent::policy_source::LoadedPolicy;
use tweezer_vision::genicam::{Acquisition, GenicamCamera, GenicamConfig, PixelFormat};
use tweezer_vision::{Camera, CameraError, FrameCounters};

/// The simulated camera's address: it listens on GVCP's fixed port, so
/// one runs at a time (the tests take [`one_camera`]).
const ADDRESS: &str = "127.0.0.1";
const SERIAL: &str = "TWEEZER1";

/// Holds the loopback camera's port for one test.
fn one_camera() -> MutexGuard<'static, ()> {
    static PORT: Mutex<()> = Mutex::new(());
    PORT.lock().unwrap_or_else(|e| e.into_inner())
}

/// Aravis's simulated GigE Vision camera, killed when dropped.
struct FakeCamera(Child);

impl FakeCamera {
    fn start() -> Self {
        Self::losing(0)
    }

    /// One that loses this many of every thousand stream packets.
    fn losing(per_thousand: u32) -> Self {
        let child = Command::new("arv-fake-gv-camera-0.8")
            .args(["-i", ADDRESS, "-s", SERIAL])
            .args(["-r", &per_thousand.to_string()])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| {
                panic!(
                    "cannot start arv-fake-gv-camera-0.8 ({e}): install Debian's aravis-tools (apt-get install aravis-tools)"
                )
            });
        // It answers once its control socket is bound.
        let deadline = Instant::now() + Duration::from_secs(20);
        while tweezer_vision::genicam::describe(ADDRESS).is_err() {
            assert!(
                Instant::now() < deadline,
                "the simulated camera never answered"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
        Self(child)
    }
}

impl Drop for FakeCamera {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn config() -> GenicamConfig {
    GenicamConfig {
        camera: ADDRESS.into(),
        ..GenicamConfig::default()
    }
}

fn open(config: &GenicamConfig) -> Result<GenicamCamera, CameraError> {
    GenicamCamera::open(config, Duration::from_secs(2), Arc::default())
}

#[test]
fn the_cameras_command_describes_the_camera_at_an_address() {
    let _port = one_camera();
    let _camera = FakeCamera::start();
    let output = Command::new(env!("CARGO_BIN_EXE_hardware-agent"))
        .args(["cameras", ADDRESS, "--json"])
        .output()
        .unwrap();
    assert!(output.status.success(), "{output:?}");
    let found: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(found["serial"], SERIAL);
    assert_eq!(found["model"], "Fake");
    assert_eq!(found["protocol"], "GigEVision");
    assert_eq!(found["address"], ADDRESS);
    let formats = found["pixel_formats"].as_array().unwrap();
    for format in ["Mono8", "Mono16"] {
        assert!(formats.iter().any(|f| f == format), "{found}");
    }
    // The id it gives opens the camera, as does its serial number.
    for name in [found["id"].as_str().unwrap(), SERIAL] {
        let camera = open(&GenicamConfig {
            camera: name.into(),
            ..config()
        });
        assert!(camera.is_ok(), "{name}: {camera:?}");
    }
}

#[test]
fn every_setting_is_read_back_and_a_missing_feature_is_refused_by_name() {
    let _port = one_camera();
    let _camera = FakeCamera::start();
    let wanted = GenicamConfig {
        pixel_format: PixelFormat::Mono16,
        exposure_us: Some(4000.0),
        gain: Some(2.0),
        roi: Some([16, 8, 320, 240]),
        binning: Some([1, 1]),
        frame_rate_hz: Some(20.0),
        ..config()
    };
    let camera = open(&wanted).unwrap();
    let settings = camera.settings();
    assert_eq!(settings.pixel_format, "Mono16");
    assert_eq!(settings.roi, [16, 8, 320, 240]);
    assert_eq!(settings.binning, Some([1, 1]));
    assert_eq!(settings.exposure_us, Some(4000.0));
    assert_eq!(settings.gain, Some(2.0));
    assert_eq!(settings.frame_rate_hz, Some(20.0));
    assert_eq!(camera.size(), [320, 240]);
    drop(camera);

    // The simulated camera has no 12-bit format.
    let refused = open(&GenicamConfig {
        pixel_format: PixelFormat::Mono12,
        ..config()
    })
    .unwrap_err()
    .to_string();
    assert!(
        refused.contains("camera.genicam.pixel_format") && refused.contains("Mono12"),
        "{refused}"
    );
    assert!(
        refused.contains("Mono16"),
        "the offered formats are listed: {refused}"
    );
    // Nor a region larger than its sensor.
    let refused = open(&GenicamConfig {
        roi: Some([0, 0, 4096, 4096]),
        ..config()
    })
    .unwrap_err()
    .to_string();
    assert!(refused.contains("camera.genicam.roi"), "{refused}");
    // An absent camera is named.
    let absent = open(&GenicamConfig {
        camera: "no-such-camera".into(),
        ..config()
    })
    .unwrap_err()
    .to_string();
    assert!(absent.contains("no-such-camera"), "{absent}");
}

/// Frames from `camera`, with the arrival times it reports.
fn grab_frames(camera: &mut GenicamCamera, n: usize) -> Vec<Instant> {
    camera.start().unwrap();
    (0..n)
        .map(|_| {
            let frame = camera.grab().unwrap();
            assert_eq!([frame.width(), frame.height()], camera.size());
            camera.captured().unwrap()
        })
        .collect()
}

#[test]
fn free_run_frames_come_at_the_configured_rate_and_software_triggers_one_at_a_time() {
    let _port = one_camera();
    let _camera = FakeCamera::start();
    let counters = Arc::new(FrameCounters::default());
    let mut camera = GenicamCamera::open(
        &GenicamConfig {
            frame_rate_hz: Some(20.0),
            roi: Some([0, 0, 256, 128]),
            ..config()
        },
        Duration::from_secs(2),
        counters.clone(),
    )
    .unwrap();
    let times = grab_frames(&mut camera, 21);
    let mut gaps: Vec<f64> = times
        .windows(2)
        .map(|w| (w[1] - w[0]).as_secs_f64())
        .collect();
    gaps.sort_by(f64::total_cmp);
    // Each grab takes the first frame after it begins: consecutive grabs
    // get consecutive frames, a period apart.
    let median = gaps[gaps.len() / 2];
    assert!((0.025..=0.1).contains(&median), "median gap {median} s");
    assert!(gaps[0] > 0.0, "a frame was handed out twice");
    camera.stop();
    assert_eq!(counters.read()[0], 21);
    // One program controls a GigE Vision camera at a time.
    drop(camera);

    let mut triggered = open(&GenicamConfig {
        acquisition: Acquisition::SoftwareTrigger,
        roi: Some([0, 0, 256, 128]),
        ..config()
    })
    .unwrap();
    let times = grab_frames(&mut triggered, 5);
    assert!(times.windows(2).all(|w| w[1] > w[0]));
    triggered.stop();
}

#[test]
fn the_bench_measures_the_time_from_a_frame_to_its_command_in_both_modes() {
    let _port = one_camera();
    let _camera = FakeCamera::start();
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("agent.toml");
    std::fs::write(
        &config,
        format!(
            "[camera]\nsource = \"genicam\"\n[camera.genicam]\ncamera = \"{ADDRESS}\"\nroi = [0, 0, 640, 480]\nframe_rate_hz = 50.0\n"
        ),
    )
    .unwrap();
    // At the shipped control rate: a step waits a control period for its
    // frame, and the simulated camera sometimes pauses 120 ms, past the
    // 100 ms period of `bench`'s default 10 Hz.
    let rate = ControlConfig::default().rate_hz.to_string();
    let output = Command::new(env!("CARGO_BIN_EXE_hardware-agent"))
        .arg("--config")
        .arg(&config)
        .args(["bench", "--camera", "20", "--rate", &rate, "--json"])
        .output()
        .unwrap();
    assert!(output.status.success(), "{output:?}");
    let figures: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(figures["control_rate_hz"], ControlConfig::default().rate_hz);
    let modes = figures["modes"].as_array().unwrap();
    let names: Vec<&str> = modes
        .iter()
        .map(|m| m["acquisition"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["free-run", "software-trigger"]);
    for mode in modes {
        assert_eq!(mode["steps"], 20);
        let (median, p99) = (
            mode["frame_to_command_ms_median"].as_f64().unwrap(),
            mode["frame_to_command_ms_p99"].as_f64().unwrap(),
        );
        // Measured, and in order; how fast is the benchmark's to say.
        assert!(0.0 < median && median <= p99, "{mode}");
        let tick = mode["tick_to_command_ms_median"].as_f64().unwrap();
        assert!(tick > 0.0, "{mode}");
    }
    eprintln!("{figures}");
}

#[test]
fn incomplete_frames_are_counted_and_never_handed_out() {
    let _port = one_camera();
    let _camera = FakeCamera::losing(150);
    let counters = Arc::new(FrameCounters::default());
    let mut camera = GenicamCamera::open(
        &GenicamConfig {
            // Three stream packets a frame: most frames arrive whole.
            roi: Some([0, 0, 64, 48]),
            frame_rate_hz: Some(100.0),
            ..config()
        },
        Duration::from_secs(2),
        counters.clone(),
    )
    .unwrap();
    grab_frames(&mut camera, 40);
    let [frames, incomplete, _] = counters.read();
    assert_eq!(frames, 40);
    assert!(incomplete > 0, "no frame lost a packet");
}

#[test]
fn a_camera_lost_mid_episode_is_a_fault_with_the_stages_stopped_then_reconnects() {
    let _port = one_camera();
    let fake = FakeCamera::start();
    // The test pattern holds no trapped sphere: the loop holds the stages
    // still, frame after frame, until it gives up. The loop runs at the
    // shipped rate: a step waits a control period for its frame, and the
    // simulated camera now and then leaves 120 ms between two frames.
    let lost_trap_frames = 40;
    let (config, control) = common::agent_config(lost_trap_frames);
    let control = ControlConfig {
        rate_hz: ControlConfig::default().rate_hz,
        ..control
    };
    let counters = Arc::new(FrameCounters::default());
    let camera = GenicamCamera::open(
        &GenicamConfig {
            frame_rate_hz: Some(50.0),
            roi: Some([0, 0, 320, 240]),
            ..self::config()
        },
        Duration::from_secs_f64(control.period_s()),
        counters.clone(),
    )
    .unwrap();
    let (mut rig, twin) = common::twin_rig(camera, &config, control);
    let mut policy = LoadedPolicy::baseline(Baseline::Greedy, &config.env);
    let halt = Halt::default();

    // The camera dies two seconds into the episode.
    let killer = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_secs(2));
        drop(fake);
    });
    let summary = rig.run_episode(policy.policy.as_mut(), [500.0, 0.0], &halt, |_| {});
    killer.join().unwrap();
    let Ending::Fault(reason) = &summary.ending else {
        panic!("the episode ended {:?}, not as a fault", summary.ending);
    };
    assert!(
        reason.contains("camera") && reason.contains("lost"),
        "{reason}"
    );
    assert!(common::still(&twin), "a stage still moves");
    let before = counters.read()[0];
    assert!(before >= 5, "{before} frames before the camera died");

    // The camera comes back: the next episode reconnects and runs until the
    // loop gives up on the (absent) trapped sphere.
    let _back = FakeCamera::start();
    let summary = rig.run_episode(policy.policy.as_mut(), [500.0, 0.0], &halt, |_| {});
    assert_eq!(summary.ending, Ending::TrapLost, "{summary:?}");
    assert!(counters.read()[0] >= before + u64::from(lost_trap_frames));
}
