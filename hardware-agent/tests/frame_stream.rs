//! Frames from another program (`[camera] source = "stream"`), written by
//! the shipped example, `python/examples/camera_feed.py`, as a real
//! process: on its standard output or into the agent's Unix socket. Its
//! demonstration frames are segmented; a program that stalls, dies or
//! writes a malformed frame ends the episode as a fault with the stages
//! stopped, and the next episode starts it again.

mod common;

use std::path::PathBuf;
use std::process::{Child, Command};
use std::sync::Arc;
use std::time::Duration;
use tweezer_gym::Baseline;
use tweezer_hardware_agent::control::{Ending, EpisodeSummary, Halt, Rig};
use tweezer_hardware_agent::policy_source::LoadedPolicy;
use tweezer_vision::frame_stream::{StreamCamera, StreamConfig};
use tweezer_vision::{Camera, FrameCounters, Segmenter};

fn feed_script() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../python/examples/camera_feed.py")
}

/// The example started by the agent, with these options.
fn program(options: &[&str]) -> StreamConfig {
    let mut command = vec!["python3".to_string(), feed_script().display().to_string()];
    command.extend(options.iter().map(|o| o.to_string()));
    StreamConfig {
        command,
        ..StreamConfig::default()
    }
}

fn open(config: &StreamConfig, counters: &Arc<FrameCounters>) -> StreamCamera {
    StreamCamera::open(config, Duration::from_millis(100), counters.clone()).unwrap_or_else(|e| {
        panic!("{e} (the example needs python3 on the PATH: apt-get install python3)")
    })
}

/// Greedy episodes toward a target 500 px to the right.
fn episode<C: Camera>(rig: &mut Rig<C, serialport::TTYPort>) -> EpisodeSummary {
    let config = common::agent_config(2).0;
    let mut policy = LoadedPolicy::baseline(Baseline::Greedy, &config.env);
    rig.run_episode(
        policy.policy.as_mut(),
        [500.0, 0.0],
        &Halt::default(),
        |_| {},
    )
}

#[test]
fn a_programs_frames_are_segmented_where_it_drew_the_spheres() {
    let counters = Arc::new(FrameCounters::default());
    let mut camera = open(&program(&["--free", "0", "--rate", "30"]), &counters);
    assert_eq!(camera.size(), [640, 480]);
    let mut segmenter = Segmenter::new(Default::default(), camera.size()).unwrap();
    for _ in 0..5 {
        let frame = camera.grab().unwrap();
        assert!(
            camera.captured().is_some(),
            "the frame said when it was exposed"
        );
        let found = segmenter.segment(&frame).unwrap();
        assert_eq!(found.len(), 1, "{found:?}");
        let [x, y] = found[0].centre;
        assert!((x - 320.0).hypot(y - 240.0) < 1.0, "found at {x}, {y}");
    }
    assert_eq!(counters.read(), [5, 0, 0]);
}

/// Runs an episode on frames from `config`'s feed, expecting a fault that
/// says `says`, with the stages stopped; then another, which must start the
/// feed again and run.
fn fault_then_restart(config: StreamConfig, says: &str) -> Arc<FrameCounters> {
    let counters = Arc::new(FrameCounters::default());
    let camera = open(&config, &counters);
    let (agent, control) = common::agent_config(2);
    let (mut rig, twin) = common::twin_rig(camera, &agent, control);
    for episode_number in 0..2 {
        let summary = episode(&mut rig);
        let Ending::Fault(reason) = &summary.ending else {
            panic!("episode {episode_number} ended {:?}", summary.ending);
        };
        assert!(reason.contains(says), "{reason}");
        // The loop drove the stages toward the target until the fault
        // (the program's first frames go by while the rig is built).
        assert!(summary.steps >= 2, "{summary:?}");
        assert!(common::still(&twin), "a stage still moves");
    }
    counters
}

#[test]
fn a_program_that_stalls_is_a_fault_and_is_restarted() {
    fault_then_restart(
        program(&["--stall-after", "40", "--rate", "30"]),
        "sent no frame within",
    );
}

#[test]
fn a_program_that_dies_is_a_fault_and_is_restarted() {
    fault_then_restart(
        program(&["--exit-after", "40", "--rate", "30"]),
        "closed its stream (exit status: 3)",
    );
}

#[test]
fn a_malformed_frame_is_counted_and_a_fault() {
    let counters = fault_then_restart(
        program(&["--garbage-after", "40", "--rate", "30"]),
        "wrote a malformed frame: a frame must start with P5",
    );
    assert_eq!(counters.read()[1], 2);
}

/// The example run on its own, writing into `socket`.
fn connect(socket: &std::path::Path) -> Child {
    Command::new("python3")
        .arg(feed_script())
        .args(["--rate", "30", "--socket"])
        .arg(socket)
        .spawn()
        .unwrap()
}

#[test]
fn a_program_feeds_the_socket_and_a_new_connection_takes_over() {
    let dir = tempfile::tempdir().unwrap();
    let socket = dir.path().join("camera.sock");
    let config = StreamConfig {
        socket: Some(socket.clone()),
        ..StreamConfig::default()
    };
    let counters = Arc::new(FrameCounters::default());
    // The agent listens first; the program connects when it is up.
    let opened = std::thread::spawn({
        let (config, counters) = (config.clone(), counters.clone());
        move || open(&config, &counters)
    });
    while !socket.exists() {
        std::thread::sleep(Duration::from_millis(20));
    }
    let mut first = connect(&socket);
    let camera = opened.join().unwrap();
    let (agent, control) = common::agent_config(2);
    let (mut rig, twin) = common::twin_rig(camera, &agent, control);

    // The program dies mid-episode: a fault, the stages stopped.
    let killer = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(700));
        first.kill().unwrap();
        first.wait().unwrap();
    });
    let summary = episode(&mut rig);
    killer.join().unwrap();
    let Ending::Fault(reason) = &summary.ending else {
        panic!("ended {:?}", summary.ending);
    };
    assert!(reason.contains("closed its stream"), "{reason}");
    assert!(common::still(&twin));

    // Another connects: the next episode runs on its frames.
    let mut second = connect(&socket);
    let killer = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(1500));
        second.kill().unwrap();
        second.wait().unwrap();
    });
    let summary = episode(&mut rig);
    killer.join().unwrap();
    assert!(summary.steps >= 3, "{summary:?}");
    drop(rig);
    assert!(!socket.exists(), "the socket outlived the camera");
}
