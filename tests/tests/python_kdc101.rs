//! The simulated KDC101 as an independent client sees it: the
//! `thorlabs-apt-device` package from PyPI (in a fresh virtual environment)
//! drives the twin's controller over its pseudo-terminal as a lab's script
//! would — parameters, homing, absolute, relative, jog and velocity moves,
//! stops, polled status and the status updates the controller sends by
//! itself — and every answer must be what the APT protocol documents.

use serde_json::Value;
use std::path::Path;
use std::time::Duration;
use tweezer_system_tests::{check, python_venv};

const COUNTS_PER_MM: f64 = 34_554.96;

#[test]
fn thorlabs_apt_device_homes_moves_and_reads_the_simulated_kdc101() {
    let dir = tempfile::tempdir().unwrap();
    let bin = python_venv(dir.path(), "requirements-kdc101.txt");
    let spawn = |serial| {
        kdc101::PtySimulator::spawn(
            serial,
            // As a KDC101 powers up: not homed.
            kdc101::ActuatorModel {
                homed: false,
                ..Default::default()
            },
            Duration::from_millis(2),
        )
        .unwrap()
    };
    let (twin, auto) = (spawn(27_000_123), spawn(27_000_124));
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("python/kdc101_client.py");
    let out = check(
        &bin.join("python"),
        &[
            script.to_str().unwrap(),
            twin.path().to_str().unwrap(),
            auto.path().to_str().unwrap(),
        ],
    );
    let seen: Value = serde_json::from_str(out.lines().last().unwrap_or_default())
        .unwrap_or_else(|e| panic!("{e}: {out}"));
    let counts = |mm: f64| (mm * COUNTS_PER_MM) as i64;

    // Parameters set are the parameters read back.
    assert_eq!(seen["velparams"], 2 * 772_981);
    assert_eq!(
        seen["homeparams"],
        serde_json::json!([2 * 772_981, counts(0.5)])
    );
    assert_eq!(seen["jogparams"], counts(0.25));
    assert_eq!(seen["enabled"], true);
    // Homing: to the reverse limit, out by the offset, counter zeroed.
    assert_eq!(seen["homed"], true, "{seen}");
    assert_eq!(seen["after_home"], 0);
    assert!(twin.controller().homed());
    for (arrived, at) in [
        ("absolute", "at_absolute"),
        ("relative", "at_relative"),
        ("jog", "after_jog"),
    ] {
        assert_eq!(seen[arrived], true, "{arrived}: {seen}");
        assert!(seen[at].is_i64(), "{seen}");
    }
    assert_eq!(seen["at_absolute"], counts(2.0));
    assert_eq!(seen["at_relative"], counts(2.0) - counts(0.5));
    // Signed velocity: its sign is the direction the position moves.
    for key in ["velocity_moving", "velocity_reversed"] {
        let [p0, v, p1] = [0, 1, 2].map(|k| seen[key][k].as_i64().unwrap());
        assert!(v != 0 && (v > 0) == (p1 > p0), "{key}: {p0} {v} {p1}");
    }
    let first = seen["velocity_moving"][1].as_i64().unwrap();
    let second = seen["velocity_reversed"][1].as_i64().unwrap();
    assert!(first.signum() == -second.signum(), "{seen}");
    assert_eq!(seen["stopped"], true);
    assert_eq!(
        seen["first_update"], true,
        "no status update within 15 s of HW_START_UPDATEMSGS: {seen}"
    );
    assert_eq!(
        seen["auto_updates"], true,
        "no status updates after HW_START_UPDATEMSGS: {seen}"
    );
    assert!(
        !twin.controller().sends_updates(),
        "HW_STOP_UPDATEMSGS at close"
    );
}
