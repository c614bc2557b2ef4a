//! Every process binary reads the same config files.

use tweezer_system_tests::{run, stderr_of_failure, stdout_of};

#[test]
fn every_process_prints_and_checks_its_config() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "[env.image]\nwidth = 300\nheight = 256\n").unwrap();
    for bin in ["learner", "hardware-agent", "actor"] {
        let text = stdout_of(&run(bin, &["config"]));
        let table: toml::Table = toml::from_str(&text).unwrap();
        assert_eq!(
            table["env"]["image"]["width"].as_integer(),
            Some(320),
            "{bin}"
        );
        let err = stderr_of_failure(&run(bin, &["--config", bad.to_str().unwrap(), "config"]));
        assert!(
            err.contains("env.image") && err.contains("aspect ratio"),
            "{bin}: {err}"
        );
    }
}
