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

/// The paper network's convolutions need 8 pixels each way: a smaller
/// image is a config error naming `env.image` (the set network reads no
/// image and takes it), and the smallest images that fit, whose last
/// feature maps are one pixel, train.
#[test]
fn images_too_small_for_the_paper_network_are_refused_and_the_smallest_train() {
    let dir = tempfile::tempdir().unwrap();
    let file = |name: &str, text: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        path.to_str().unwrap().to_string()
    };
    let tiny = file("tiny.toml", "[env.image]\nwidth = 5\nheight = 4\n");
    let err = stderr_of_failure(&run("learner", &["--config", &tiny, "config"]));
    assert!(
        err.contains("env.image") && err.contains("too small for the paper network"),
        "{err}"
    );
    let set = file(
        "set.toml",
        "[env.image]\nwidth = 5\nheight = 4\n[learner.network]\nkind = \"set\"\n",
    );
    stdout_of(&run("learner", &["--config", &set, "config"]));
    for [width, height] in [[10, 8], [15, 12]] {
        let small = file(
            &format!("{width}x{height}.toml"),
            &format!("[env.image]\nwidth = {width}\nheight = {height}\n"),
        );
        let bench = stdout_of(&run(
            "learner",
            &[
                "--config",
                &small,
                "bench",
                "--json",
                "--updates",
                "2",
                "--replay-capacity",
                "2000",
            ],
        ));
        let report: serde_json::Value = serde_json::from_str(bench.trim()).unwrap();
        assert!(
            report["update_ms_mean"]
                .as_f64()
                .is_some_and(f64::is_finite),
            "{bench}"
        );
    }
}
