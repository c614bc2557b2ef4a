//! The driver against simulated KDC101s whose hardware fails on a
//! pseudo-terminal: a runaway motor, a frozen encoder, a counter that
//! jumps, a controller that power-cycles or resets, a limit switch that
//! trips, and replies addressed from another device. Each is a fault that
//! names its cause; the motor stops at once, and the driver never moves it
//! again. Also: stages never homed are refused until homed, and an
//! unplugged controller is named and said to be out of reach of any stop.

use kdc101::apt::{AptError, Channel, Reply, Z8Units};
use kdc101::{
    ActuatorModel, Axis, AxisLimits, Commanded, Malfunction, PtySimulator, SimulatedController,
    open_port,
};
use std::time::{Duration, Instant};

const LIMITS: AxisLimits = AxisLimits {
    min_mm: 0.5,
    max_mm: 11.5,
    max_speed_mm_s: 2.0,
    acceleration_mm_s2: 4.0,
    command_interval_s: 0.2,
};
/// The control period the tests command at, as the agent does.
const PERIOD: Duration = Duration::from_millis(100);

fn twin(model: ActuatorModel) -> PtySimulator {
    PtySimulator::spawn(27_000_001, model, Duration::from_millis(2)).unwrap()
}

fn connect(twin: &PtySimulator) -> Axis<serialport::TTYPort> {
    let port = open_port(twin.path()).unwrap();
    Axis::connect(port, Z8Units::default(), LIMITS, Duration::from_millis(300))
        .unwrap()
        .0
}

/// Commands `speed(k)` at the `k`th period, as the agent's loop does (read,
/// then command), calling `fail` before the `at`th command, until the driver
/// refuses; the error, the commands that went before it, and the farthest
/// the motor went from where it was when `fail` was called, mm.
fn drive_until_refused(
    twin: &PtySimulator,
    stage: &mut Axis<serialport::TTYPort>,
    speed: impl Fn(usize) -> f64,
    at: usize,
    fail: impl FnOnce(&mut SimulatedController),
) -> (AptError, usize, f64) {
    let motor = |twin: &PtySimulator| twin.controller().carriage_mm();
    let mut fail = Some(fail);
    let mut from = motor(twin);
    let mut farthest: f64 = 0.0;
    for step in 0..50 {
        if step == at {
            from = motor(twin);
            twin.with_controller(fail.take().unwrap());
        }
        let commanded = (stage.position_mm()).and_then(|_| stage.set_velocity(speed(step)));
        if step >= at {
            farthest = farthest.max((motor(twin) - from).abs());
        }
        match commanded {
            Ok(Commanded::Moving(_)) => {}
            Ok(Commanded::Stopped) if speed(step) == 0.0 => {}
            Ok(Commanded::Stopped) => panic!("stopped at a soft limit at step {step}"),
            Err(e) => {
                assert!(step >= at, "refused before the failure: {e}");
                let still = until_still(twin);
                farthest = farthest.max((motor(twin) - from).abs());
                assert!(still < Duration::from_millis(250), "{still:?} to stop");
                return (e, step - at, farthest);
            }
        }
        std::thread::sleep(PERIOD);
    }
    panic!("the driver never noticed")
}

/// Two simulated controllers (X, Y) and the stage pair driving them.
fn pair_of_twins() -> (
    PtySimulator,
    PtySimulator,
    kdc101::StagePair<serialport::TTYPort>,
) {
    let latency = Duration::from_millis(2);
    let [x, y] = [27_000_001, 27_000_002]
        .map(|serial| PtySimulator::spawn(serial, ActuatorModel::default(), latency).unwrap());
    let (pair, _) = kdc101::StagePair::open_paths(
        [x.path(), y.path()],
        &kdc101::StagesConfig::default(),
        Duration::from_millis(350),
    )
    .unwrap();
    (x, y, pair)
}

/// Waits until the simulated motor stands still; how long that took.
fn until_still(twin: &PtySimulator) -> Duration {
    let start = Instant::now();
    while twin.controller().speed_mm_s() != 0.0 {
        assert!(start.elapsed() < Duration::from_secs(2), "still moving");
        std::thread::sleep(Duration::from_millis(2));
    }
    start.elapsed()
}

/// The driver refuses to move the stage again, and the motor stays put.
fn never_moves_again(twin: &PtySimulator, stage: &mut Axis<serialport::TTYPort>, cause: &str) {
    let before = twin.controller().carriage_mm();
    for _ in 0..3 {
        let refused = stage.set_velocity(1.0).unwrap_err();
        assert!(refused.to_string().contains(cause), "{refused}");
        assert!(
            refused.to_string().contains("restart the agent"),
            "{refused}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(stage.position_mm().is_err());
    assert_eq!(twin.controller().speed_mm_s(), 0.0);
    assert_eq!(twin.controller().carriage_mm(), before);
}

fn untrusted(error: &AptError, cause: &str) {
    assert!(
        matches!(error, AptError::Untrusted(why) if why.contains(cause)),
        "{error}"
    );
}

#[test]
fn a_runaway_motor_is_stopped_as_soon_as_it_outruns_the_command() {
    let twin = twin(ActuatorModel::default());
    let mut stage = connect(&twin);
    let (error, late, farthest) = drive_until_refused(
        &twin,
        &mut stage,
        |_| 0.5,
        5,
        |c| c.set_malfunction(Some(Malfunction::Runaway(3.0))),
    );
    untrusted(&error, "runaway");
    // From 0.5 toward 1.5 mm/s at 4 mm/s²: a period's travel outgrows the
    // allowance within two or three periods.
    assert!(late <= 3, "noticed {late} commands late");
    println!("runaway: {farthest:.3} mm from the failure to the stop");
    never_moves_again(&twin, &mut stage, "runaway");
}

#[test]
fn a_frozen_encoder_is_noticed_within_two_readings() {
    let twin = twin(ActuatorModel::default());
    let mut stage = connect(&twin);
    let (error, late, farthest) = drive_until_refused(
        &twin,
        &mut stage,
        |_| 1.0,
        5,
        |c| c.set_malfunction(Some(Malfunction::FrozenEncoder)),
    );
    untrusted(&error, "frozen encoder");
    assert!(late <= 3, "noticed {late} commands late");
    println!("frozen encoder: {farthest:.3} mm from the failure to the stop");
    never_moves_again(&twin, &mut stage, "frozen encoder");
}

#[test]
fn a_frozen_encoder_is_noticed_under_moves_that_stop_and_start() {
    let twin = twin(ActuatorModel::default());
    let mut stage = connect(&twin);
    let start_stop = |step: usize| if step.is_multiple_of(2) { 2.0 } else { 0.0 };
    let (error, late, farthest) = drive_until_refused(&twin, &mut stage, start_stop, 4, |c| {
        c.set_malfunction(Some(Malfunction::FrozenEncoder))
    });
    println!("frozen encoder, stop and start: {farthest:.3} mm, {late} commands late");
    untrusted(&error, "frozen encoder");
    // Each start and each stop moves it 20 µm here: the model's error
    // must grow past its tolerance twice.
    assert!(late <= 6, "noticed {late} commands late");
    assert!(farthest < 0.25, "{farthest} mm");
    never_moves_again(&twin, &mut stage, "frozen encoder");
}

#[test]
fn stops_from_the_pair_stopper_are_not_taken_for_a_fault() {
    let (_x, _y, mut pair) = pair_of_twins();
    for _ in 0..3 {
        for _ in 0..3 {
            pair.set_velocity_px([2000.0, -2000.0]).unwrap();
            std::thread::sleep(PERIOD);
        }
        // An e-stop or the watchdog, behind the drivers' backs.
        pair.stopper().stop_now().unwrap();
        for _ in 0..3 {
            std::thread::sleep(PERIOD);
            pair.position_mm().unwrap();
        }
    }
}

#[test]
fn a_counter_that_jumps_is_never_used() {
    let twin = twin(ActuatorModel::default());
    let mut stage = connect(&twin);
    // From about 6 mm to about 20: inside a Z825's travel, so not garbled.
    let (error, late, _) =
        drive_until_refused(&twin, &mut stage, |_| 0.5, 4, |c| c.jump_counter(14.0));
    untrusted(&error, "jumped");
    assert_eq!(late, 0);
    never_moves_again(&twin, &mut stage, "jumped");
}

#[test]
fn a_controller_that_power_cycles_mid_move_is_not_driven_on() {
    let twin = twin(ActuatorModel::default());
    let mut stage = connect(&twin);
    let (error, late, _) = drive_until_refused(&twin, &mut stage, |_| 1.0, 4, |c| c.power_cycle());
    untrusted(&error, "reset");
    assert_eq!(late, 0);
    never_moves_again(&twin, &mut stage, "reset");
}

#[test]
fn a_controller_that_goes_quiet_and_comes_back_reset_is_not_taken_back() {
    let twin = twin(ActuatorModel::default());
    let mut stage = connect(&twin);
    stage.position_mm().unwrap();
    stage.set_velocity(1.0).unwrap();
    std::thread::sleep(PERIOD);
    stage.position_mm().unwrap();
    // Silent past the reply timeout; back after 1.2 s with its counter at 0.
    twin.set_fault(Some(kdc101::Fault::Silent));
    assert!(matches!(stage.set_velocity(1.0), Err(AptError::Timeout(_))));
    std::thread::sleep(Duration::from_millis(900));
    twin.with_controller(|c| c.power_cycle());
    twin.set_fault(None);
    let error = stage.position_mm().unwrap_err();
    untrusted(&error, "reset");
    never_moves_again(&twin, &mut stage, "reset");
}

#[test]
fn a_tripped_limit_switch_is_a_fault_that_names_it() {
    // A limit switch at 7 mm, inside the 11.5 mm soft limit: the soft
    // limits do not match the actuator.
    let twin = twin(ActuatorModel {
        travel_mm: 7.0,
        ..ActuatorModel::default()
    });
    let mut stage = connect(&twin);
    let (error, _, _) = drive_until_refused(&twin, &mut stage, |_| 2.0, 0, |_| {});
    untrusted(&error, "forward hardware limit switch");
    assert!(error.to_string().contains("status bits"), "{error}");
    never_moves_again(&twin, &mut stage, "limit switch");
}

#[test]
fn replies_from_or_for_another_device_are_discarded() {
    let twin = twin(ActuatorModel::default());
    let mut stage = connect(&twin);
    let position = |source: u8, dest: u8| {
        let mut bytes = Reply::Position(Channel(1), 1_000_000).to_frame().encode();
        bytes[4] = dest | 0x80;
        bytes[5] = source;
        bytes
    };
    for _ in 0..3 {
        // Another device's answer (source 0x22), and one for another host
        // (destination 0x02), each ahead of the controller's own.
        twin.inject(&position(0x22, 0x01));
        twin.inject(&position(0x50, 0x02));
        std::thread::sleep(Duration::from_millis(20));
        let read = stage.position_mm().unwrap();
        assert!((read - 6.0).abs() < 1e-4, "read {read} mm");
    }
}

#[test]
fn swapped_ports_are_refused_by_serial_number() {
    use kdc101::{StagePair, StagesConfig, StagesError};
    let latency = Duration::from_millis(2);
    let stages = [27_000_001, 27_000_002]
        .map(|serial| PtySimulator::spawn(serial, ActuatorModel::default(), latency).unwrap());
    let config = StagesConfig {
        x_serial: Some(27_000_002),
        y_serial: Some(27_000_001),
        ..StagesConfig::default()
    };
    let paths = [stages[0].path(), stages[1].path()];
    let error = StagePair::open_paths(paths, &config, Duration::from_millis(350)).unwrap_err();
    assert!(
        matches!(
            error,
            StagesError::Serial {
                axis: "X",
                expected: 27_000_002,
                found: 27_000_001,
                ..
            }
        ),
        "{error}"
    );
    let message = error.to_string();
    for needed in [
        "27000001",
        "27000002",
        "stages.x_serial",
        "/dev/serial/by-id/",
    ] {
        assert!(message.contains(needed), "{message}");
    }
    // The right way round, it connects.
    let swapped = StagesConfig {
        x_serial: Some(27_000_001),
        y_serial: Some(27_000_002),
        ..StagesConfig::default()
    };
    StagePair::open_paths(paths, &swapped, Duration::from_millis(350)).unwrap();
}

#[test]
fn a_controller_that_reset_is_found_by_its_lost_homing() {
    let twin = twin(ActuatorModel::default());
    let mut stage = connect(&twin);
    assert!(stage.homed());
    stage.position_mm().unwrap();
    // Reset while still, its counter set back to where it was: only the
    // status tells, in the MOVE_STOPPED that answers the next stop.
    twin.with_controller(|c| {
        let at = c.status().position;
        c.power_cycle();
        c.jump_counter(Z8Units::default().mm(at));
    });
    stage.stop(kdc101::apt::StopMode::Profiled).unwrap();
    std::thread::sleep(Duration::from_millis(20));
    let error = stage.position_mm().unwrap_err();
    untrusted(&error, "no longer homed");
    never_moves_again(&twin, &mut stage, "no longer homed");
}

#[test]
fn homing_parks_the_stage_mid_travel_and_driving_goes_on_from_there() {
    let twin = twin(ActuatorModel {
        start_mm: 1.5,
        homed: false,
        ..ActuatorModel::default()
    });
    let mut stage = connect(&twin);
    assert!(!stage.homed());
    let parked = stage.home().unwrap();
    assert_eq!(parked, 0.5 * (LIMITS.min_mm + LIMITS.max_mm));
    assert!(stage.homed() && twin.controller().homed());
    assert!((twin.controller().carriage_mm() - parked).abs() < 0.01);
    assert!((stage.position_mm().unwrap() - parked).abs() < 1e-3);
    assert_eq!(stage.set_velocity(1.0).unwrap(), Commanded::Moving(1.0));
    std::thread::sleep(PERIOD);
    assert!(stage.position_mm().unwrap() > parked);
}

#[test]
fn stages_not_homed_since_power_up_are_refused_until_homed() {
    use kdc101::{StagePair, StagesConfig, StagesError};
    let latency = Duration::from_millis(2);
    let model = ActuatorModel {
        start_mm: 1.0,
        homed: false,
        ..ActuatorModel::default()
    };
    let stages =
        [27_000_001, 27_000_002].map(|serial| PtySimulator::spawn(serial, model, latency).unwrap());
    let paths = [stages[0].path(), stages[1].path()];
    let interval = Duration::from_millis(350);
    let error = StagePair::open_paths(paths, &StagesConfig::default(), interval).unwrap_err();
    assert!(
        matches!(
            error,
            StagesError::NotHomed {
                axis: "X",
                serial: 27_000_001
            }
        ),
        "{error}"
    );
    assert!(error.to_string().contains("hardware-agent home"), "{error}");
    let homing = StagesConfig {
        require_homed: false,
        ..StagesConfig::default()
    };
    let (mut pair, _) = StagePair::open_paths(paths, &homing, interval).unwrap();
    assert_eq!(pair.home().unwrap(), [6.0, 6.0]);
    drop(pair);
    StagePair::open_paths(paths, &StagesConfig::default(), interval).unwrap();
}

#[test]
fn an_unplugged_controller_is_named_and_said_to_be_unstoppable_from_here() {
    let (x, y, mut pair) = pair_of_twins();
    pair.set_velocity_px([2000.0, 2000.0]).unwrap();
    std::thread::sleep(PERIOD);
    assert!(y.controller().speed_mm_s() > 0.0);
    drop(x);
    let error = pair.set_velocity_px([2000.0, 2000.0]).unwrap_err();
    let message = error.to_string();
    assert!(message.starts_with("stage X: serial I/O"), "{message}");
    assert!(message.contains("may still be moving"), "{message}");
    // The other stage is stopped at once.
    until_still(&y);
}
