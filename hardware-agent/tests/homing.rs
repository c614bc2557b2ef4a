//! `hardware-agent home` as a process, against two simulated KDC101s on
//! pseudo-terminals that powered up un-homed.

use kdc101::{ActuatorModel, PtySimulator};
use serde_json::Value;
use std::process::Command;
use std::time::Duration;
use tweezer_system_tests::output_of;

#[test]
fn home_homes_both_stages_and_parks_them_mid_travel() {
    let model = ActuatorModel {
        start_mm: 1.0,
        homed: false,
        ..ActuatorModel::default()
    };
    let latency = Duration::from_millis(2);
    let stages =
        [27_000_011, 27_000_012].map(|serial| PtySimulator::spawn(serial, model, latency).unwrap());
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("agent.toml");
    std::fs::write(
        &config,
        format!(
            "[stages]\nx_port = {:?}\ny_port = {:?}\nx_serial = 27000011\n",
            stages[0].path(),
            stages[1].path()
        ),
    )
    .unwrap();
    let out = output_of(
        Command::new(env!("CARGO_BIN_EXE_hardware-agent"))
            .arg("--config")
            .arg(&config)
            .arg("home"),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let line: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(line["parked_mm"], serde_json::json!([6.0, 6.0]), "{line}");
    assert_eq!(line["x_serial"], 27_000_011);
    assert_eq!(line["y_serial"], 27_000_012);
    // The unset serial is named, with the line to add.
    assert!(stderr.contains("y_serial = 27000012"), "{stderr}");
    assert!(!stderr.contains("x_serial = "), "{stderr}");
    for stage in &stages {
        let controller = stage.controller();
        assert!(controller.homed());
        assert!((controller.carriage_mm() - 6.0).abs() < 0.01);
        assert_eq!(controller.speed_mm_s(), 0.0);
    }
}
