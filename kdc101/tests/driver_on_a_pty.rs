//! The axis driver and the stage pair over a real serial-port stack,
//! against simulated KDC101s on pseudo-terminals: identify, move, read,
//! stop, and stop on every kind of bad reply.

use kdc101::apt::{AptError, StopMode, Z8Units};
use kdc101::{ActuatorModel, Axis, AxisLimits, Commanded, Fault, PtySimulator, open_port};
use std::time::{Duration, Instant};

const LIMITS: AxisLimits = AxisLimits {
    min_mm: 0.5,
    max_mm: 11.5,
    max_speed_mm_s: 2.0,
    acceleration_mm_s2: 4.0,
    command_interval_s: 0.5,
};

fn connect(twin: &PtySimulator) -> Axis<serialport::TTYPort> {
    connect_within(twin, LIMITS)
}

fn connect_within(twin: &PtySimulator, limits: AxisLimits) -> Axis<serialport::TTYPort> {
    let port = open_port(twin.path()).unwrap();
    let (stage, info) =
        Axis::connect(port, Z8Units::default(), limits, Duration::from_millis(300)).unwrap();
    assert_eq!(info.serial, 27_000_001);
    assert_eq!(info.model, "KDC101");
    stage
}

fn twin() -> PtySimulator {
    PtySimulator::spawn(
        27_000_001,
        ActuatorModel::default(),
        Duration::from_millis(2),
    )
    .unwrap()
}

/// Waits until the simulated motor stands still; how long that took.
fn until_still(twin: &PtySimulator) -> Duration {
    let start = Instant::now();
    while twin.controller().speed_mm_s() != 0.0 {
        assert!(
            start.elapsed() < Duration::from_secs(2),
            "the motor kept moving"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
    start.elapsed()
}

#[test]
fn the_driver_identifies_moves_reads_and_stops_the_twin_over_a_serial_port() {
    let twin = twin();
    let mut stage = connect(&twin);
    let start = stage.position_mm().unwrap();
    assert!((start - 6.0).abs() < 1e-4, "{start}");

    assert_eq!(stage.set_velocity(0.5).unwrap(), Commanded::Moving(0.5));
    std::thread::sleep(Duration::from_millis(400));
    let moved = stage.position_mm().unwrap() - start;
    // 0.4 s at 0.5 mm/s, less the 62.5 ms of acceleration: ~0.18 mm.
    assert!((0.12..0.5).contains(&moved), "{moved}");
    assert!((twin.controller().speed_mm_s() - 0.5).abs() < 1e-5);

    // Reversal, clamping, then a profiled stop.
    assert_eq!(stage.set_velocity(-9.0).unwrap(), Commanded::Moving(-2.0));
    std::thread::sleep(Duration::from_millis(300));
    // From +0.5 toward -2 mm/s at 4 mm/s²: about -0.7 mm/s by now.
    let speed = twin.controller().speed_mm_s();
    assert!((-2.0..-0.4).contains(&speed), "{speed}");
    stage.stop(StopMode::Profiled).unwrap();
    until_still(&twin);
    let position = stage.position_mm().unwrap();
    let motor = Z8Units::default().mm(Z8Units::default().counts(twin.controller().carriage_mm()));
    assert!(
        (position - motor).abs() < 0.009,
        "{position} vs carriage {motor}"
    );
}

#[test]
fn a_silent_truncated_unexpected_or_failing_reply_is_an_error_and_the_motor_stops() {
    for fault in [
        Fault::Silent,
        Fault::Truncated,
        Fault::Unexpected,
        Fault::Failing,
        Fault::Straggler(Duration::from_millis(450)),
    ] {
        let twin = twin();
        let mut stage = connect(&twin);
        stage.set_velocity(2.0).unwrap();
        std::thread::sleep(Duration::from_millis(600));
        assert!(twin.controller().speed_mm_s() > 1.9);
        twin.set_fault(Some(fault));
        let started = Instant::now();
        let error = stage.position_mm().unwrap_err();
        let waited = started.elapsed();
        match fault {
            Fault::Silent | Fault::Truncated | Fault::Late(_) => {
                assert!(matches!(error, AptError::Timeout(_)), "{fault:?}: {error}");
                // The 300 ms reply timeout, not an endless wait; the slack
                // is for a loaded 2-core machine.
                assert!(waited < Duration::from_secs(1), "{waited:?}");
            }
            Fault::Unexpected | Fault::Straggler(_) => {
                assert!(
                    matches!(error, AptError::Unexpected(_)),
                    "{fault:?}: {error}"
                );
            }
            Fault::Failing => {
                assert!(
                    matches!(error, AptError::Device { .. }),
                    "{fault:?}: {error}"
                );
            }
        }
        // The immediate stop went out with the error: no 0.5 s profile.
        assert!(until_still(&twin) < Duration::from_millis(250), "{fault:?}");
    }
}

#[test]
fn dropping_the_driver_stops_the_motor() {
    let twin = twin();
    let mut stage = connect(&twin);
    stage.set_velocity(-2.0).unwrap();
    std::thread::sleep(Duration::from_millis(100));
    drop(stage);
    assert!(until_still(&twin) < Duration::from_millis(250));
}

#[test]
fn a_reversal_takes_up_the_backlash_within_one_command_interval() {
    let twin = twin(); // 8 µm of backlash
    let limits = AxisLimits {
        command_interval_s: 0.25,
        ..LIMITS
    };
    let mut stage = connect_within(&twin, limits).with_backlash(0.008);
    let carriage = || twin.controller().carriage_mm();
    let stop_and_check_the_estimate = |stage: &mut Axis<_>, twin: &PtySimulator| {
        stage.stop(StopMode::Profiled).unwrap();
        until_still(twin);
        let (estimate, carriage) = (
            stage.carriage_mm().unwrap(),
            twin.controller().carriage_mm(),
        );
        assert!(
            (estimate - carriage).abs() < 0.0005,
            "{estimate} vs {carriage}"
        );
    };

    // The first move takes up the play too: which side it is on is unknown.
    let Commanded::Moving(speed) = stage.set_velocity(0.02).unwrap() else {
        panic!("refused")
    };
    assert!((speed - 0.052).abs() < 1e-9, "{speed}");
    std::thread::sleep(Duration::from_millis(300));
    stop_and_check_the_estimate(&mut stage, &twin);

    // Reversing: 0.02 mm/s plus 8 µm over 0.25 s.
    let before = carriage();
    let Commanded::Moving(speed) = stage.set_velocity(-0.02).unwrap() else {
        panic!("refused")
    };
    assert!((speed + 0.052).abs() < 1e-9, "{speed}");
    std::thread::sleep(Duration::from_millis(250));
    stage.set_velocity(-0.02).unwrap();
    let after_one = carriage();
    // Without the boost the carriage would not have moved yet (5 µm of the
    // 8 µm of play taken up); with it, it has moved.
    assert!(before - after_one > 0.003, "moved {}", before - after_one);
    stop_and_check_the_estimate(&mut stage, &twin);
}

#[test]
fn the_stopper_halts_both_stages_at_once_whatever_their_drivers_do() {
    use kdc101::{StagePair, StagesConfig};
    let latency = Duration::from_millis(2);
    let stages = [27_000_001, 27_000_002]
        .map(|serial| PtySimulator::spawn(serial, ActuatorModel::default(), latency).unwrap());
    let (mut pair, infos) = StagePair::open_paths(
        [stages[0].path(), stages[1].path()],
        &StagesConfig::default(),
        Duration::from_millis(350),
    )
    .unwrap();
    assert_eq!(infos.map(|i| i.serial), [27_000_001, 27_000_002]);
    // 200 px/s along image x, 100 along y.
    pair.set_velocity_px([200.0, 100.0]).unwrap();
    std::thread::sleep(Duration::from_millis(200));
    let [x, y] = &stages;
    assert!(x.controller().speed_mm_s() > 0.0 && y.controller().speed_mm_s() > 0.0);
    // The stopper works from another thread while the pair stays in use.
    let stopper = pair.stopper();
    let asked = Instant::now();
    std::thread::spawn(move || stopper.stop_now().unwrap())
        .join()
        .unwrap();
    until_still(x);
    until_still(y);
    // An immediate stop, not the 0.5 s deceleration profile (2 mm/s at
    // 4 mm/s²); half of that leaves a loaded 2-core machine room.
    let latency = asked.elapsed();
    assert!(latency < Duration::from_millis(250), "{latency:?}");
    // The driver's estimate of the carriages (the first move took up the
    // backlash) is the twin's truth.
    let estimate = pair.position_mm().unwrap();
    let truth = [0, 1].map(|k| stages[k].controller().carriage_mm());
    for axis in 0..2 {
        assert!(
            (estimate[axis] - truth[axis]).abs() < 5e-4,
            "{estimate:?} vs {truth:?}"
        );
    }
}

/// The twin's position counter now, mm.
fn counter_mm(twin: &PtySimulator) -> f64 {
    Z8Units::default().mm(twin.controller().status().position)
}

#[test]
fn after_a_late_reply_or_half_a_frame_every_position_read_is_fresh() {
    for fault in [Fault::Late(Duration::from_millis(450)), Fault::Truncated] {
        let twin = twin();
        let mut stage = connect(&twin);
        twin.set_fault(Some(fault));
        let error = stage.position_mm().unwrap_err();
        assert!(matches!(error, AptError::Timeout(_)), "{fault:?}: {error}");
        twin.set_fault(None);
        // Moving, so that every reply carries another position: one that
        // answers an earlier request is at least 0.1 mm off.
        assert_eq!(stage.set_velocity(1.0).unwrap(), Commanded::Moving(1.0));
        for _ in 0..5 {
            std::thread::sleep(Duration::from_millis(150));
            let read = stage.position_mm().unwrap();
            let truth = counter_mm(&twin);
            assert!(
                (read - truth).abs() < 0.02,
                "{fault:?}: read {read} mm, the counter is at {truth} mm"
            );
        }
    }
}

#[test]
fn a_reply_that_comes_after_later_ones_is_never_taken_for_a_fresh_one() {
    let twin = twin();
    let mut stage = connect(&twin);
    let mut errors = Vec::new();
    let mut refused = |e: AptError| {
        // A stale reading taken would look like a counter that jumped.
        assert!(!matches!(e, AptError::Untrusted(_)), "{e}");
        errors.push(e.to_string());
    };
    let mut fresh = 0;
    for _ in 0..3 {
        twin.set_fault(Some(Fault::Straggler(Duration::from_millis(450))));
        let started = Instant::now();
        let mut moving = false;
        while started.elapsed() < Duration::from_millis(900) {
            // Moving, so that a reply to a request 450 ms earlier is
            // 0.2 mm off. Every error stops the motor.
            if !moving {
                match stage.set_velocity(0.5) {
                    Ok(_) => moving = true,
                    Err(e) => {
                        refused(e);
                        continue;
                    }
                }
            }
            std::thread::sleep(Duration::from_millis(50));
            let before = counter_mm(&twin);
            match stage.position_mm() {
                Ok(read) => {
                    let after = counter_mm(&twin);
                    assert!(
                        (before - 1e-3..=after + 1e-3).contains(&read),
                        "read {read} mm, the counter went from {before} to {after} mm"
                    );
                    fresh += 1;
                }
                Err(e) => {
                    refused(e);
                    moving = false;
                }
            }
        }
    }
    // Each straggler is missed where it was asked for, and found extra
    // where it came.
    let count = |what: &str| errors.iter().filter(|e| e.contains(what)).count();
    assert_eq!(count("no position reply"), 3, "{errors:?}");
    assert_eq!(count("2 position replies"), 3, "{errors:?}");
    assert_eq!(errors.len(), 6, "{errors:?}");
    assert!(fresh >= 10, "{fresh} fresh readings");
}

#[test]
fn stale_bytes_in_the_port_at_open_are_purged() {
    let twin = twin();
    twin.inject(&[0x12, 0x34, 0x00, 0x00, 0x01]);
    std::thread::sleep(Duration::from_millis(20));
    let mut stage = connect(&twin);
    let position = stage.position_mm().unwrap();
    assert!((position - 6.0).abs() < 1e-4, "{position}");
}

#[test]
fn noise_between_replies_never_reaches_the_soft_limit_check() {
    let twin = twin();
    let mut stage = connect(&twin);
    stage.set_velocity(0.5).unwrap();
    for _ in 0..20 {
        // Half a position reply's worth of noise, then the real replies.
        twin.inject(&[0x12, 0x04, 0x06, 0x00, 0x81, 0x50, 0xff]);
        match stage.set_velocity(0.5) {
            Ok(_)
            | Err(AptError::Timeout(_) | AptError::Unexpected(_) | AptError::Length { .. }) => {}
            Err(other) => panic!("{other}"),
        }
        let read = stage.position_mm();
        if let Ok(read) = read {
            assert!((read - counter_mm(&twin)).abs() < 0.02, "read {read} mm");
        }
    }
    // Quiet again: in step, reading the truth.
    std::thread::sleep(Duration::from_millis(100));
    let read = stage.position_mm().unwrap();
    assert!((read - counter_mm(&twin)).abs() < 0.02);
}
