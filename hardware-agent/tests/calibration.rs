//! `hardware-agent calibrate --twin`, run as a process against a twin whose
//! true calibration (`[twin.truth]`) and backlash differ from what
//! `[stages]` says: it must find the truth (px per µm within 1 %, the axis
//! mapping and signs exactly, the backlash within 1 µm) and write it into
//! the config file, keeping the rest; a scene without free spheres is
//! refused.

use serde_json::Value;
use std::path::Path;
use std::process::Command;
use tweezer_hardware_agent::config::AgentConfig;

/// Runs `calibrate --twin --json` with `config` written to `file`.
fn calibrate(file: &Path, config: &str, extra: &[&str]) -> (bool, String, String) {
    std::fs::write(file, config).unwrap();
    let output = Command::new(env!("CARGO_BIN_EXE_hardware-agent"))
        .arg("--config")
        .arg(file)
        .args(["calibrate", "--twin", "--json"])
        .args(extra)
        .output()
        .unwrap();
    (
        output.status.success(),
        String::from_utf8_lossy(&output.stdout).into_owned(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}

#[test]
fn calibrate_finds_the_twins_true_calibration_and_writes_it() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("agent.toml");
    let config = r#"# The lab's agent.
[stages]
px_per_um = 10.8   # typed in, and wrong
image_x = "x"
x_sign = 1.0
y_sign = 1.0
max_speed_mm_s = 2.0

[twin]
backlash_um = 6.0

[twin.truth]
px_per_um = 9.7
image_x = "y"
x_sign = -1.0
y_sign = 1.0
"#;
    let write = file.to_str().unwrap();
    let (ok, stdout, stderr) = calibrate(&file, config, &["--write", write]);
    assert!(ok, "{stderr}");
    let found: Value = serde_json::from_str(&stdout).unwrap();
    let px_per_um = found["px_per_um"].as_f64().unwrap();
    assert!((px_per_um / 9.7 - 1.0).abs() < 0.01, "{found}");
    assert_eq!(found["image_x"], "y");
    assert_eq!(found["x_sign"], -1.0);
    assert_eq!(found["y_sign"], 1.0);
    for backlash in found["backlash_um"].as_array().unwrap() {
        assert!((backlash.as_f64().unwrap() - 6.0).abs() < 1.0, "{found}");
    }
    assert!(found["residual_px"].as_f64().unwrap() < 2.0, "{found}");

    // The file now says so, and keeps the rest.
    let written = std::fs::read_to_string(&file).unwrap();
    assert!(written.starts_with("# The lab's agent."), "{written}");
    assert!(written.contains("max_speed_mm_s = 2.0"), "{written}");
    assert!(written.contains("residual"), "{written}");
    let loaded = AgentConfig::load(Some(&file)).unwrap();
    assert!((loaded.stages.px_per_um - px_per_um).abs() < 1e-3);
    assert_eq!(loaded.stages.image_x, kdc101::ImageAxis::Y);
    assert_eq!([loaded.stages.x_sign, loaded.stages.y_sign], [-1.0, 1.0]);
    assert!((loaded.stages.backlash_um - 6.0).abs() < 1.0);

    // Calibrated, the twin agrees with itself: a second run finds the same.
    let (ok, stdout, stderr) = calibrate(&file, &written, &[]);
    assert!(ok, "{stderr}");
    let again: Value = serde_json::from_str(&stdout).unwrap();
    assert!((again["px_per_um"].as_f64().unwrap() / 9.7 - 1.0).abs() < 0.01);
}

#[test]
fn a_scene_without_free_spheres_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("agent.toml");
    let (ok, _, stderr) = calibrate(
        &file,
        "[env]\nmin_free_spheres = 0\nmax_free_spheres = 0\n",
        &[],
    );
    assert!(!ok);
    assert!(stderr.contains("the scene has no features"), "{stderr}");
}
