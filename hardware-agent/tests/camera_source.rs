//! The `[camera]` table as the command line meets it: a camera source that
//! conflicts with `--twin` is refused rather than ignored, and a GenICam
//! camera in a build without Aravis says how to get one.

use std::process::Command;

/// `hardware-agent run` with `config` and `args`: its exit status and
/// standard error.
fn run_with(config: &str, args: &[&str]) -> (bool, String) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("agent.toml");
    std::fs::write(&file, config).unwrap();
    let output = Command::new(env!("CARGO_BIN_EXE_hardware-agent"))
        .arg("--config")
        .arg(&file)
        .arg("run")
        .args(args)
        .arg("--records")
        .arg(dir.path())
        .output()
        .unwrap();
    (
        output.status.success(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}

#[test]
fn a_camera_source_other_than_the_twin_is_refused_under_twin() {
    for source in ["replay", "genicam"] {
        let (ok, stderr) = run_with(
            &format!("[camera]\nsource = \"{source}\"\n"),
            &["--twin", "--greedy"],
        );
        assert!(!ok);
        assert!(
            stderr.contains(&format!(
                "camera.source = \"{source}\" conflicts with --twin"
            )),
            "{stderr}"
        );
    }
}

#[cfg(not(feature = "aravis"))]
#[test]
fn a_genicam_camera_in_a_build_without_aravis_names_the_feature() {
    let (ok, stderr) = run_with(
        "[camera]\nsource = \"genicam\"\n",
        &["--greedy", "--target-um", "10,0"],
    );
    assert!(!ok);
    assert!(
        stderr.contains("--features tweezer-hardware-agent/aravis"),
        "{stderr}"
    );
}
