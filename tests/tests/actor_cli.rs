//! The `actor` binary's commands, run as real processes.

use serde_json::Value;
use tweezer_system_tests::{run, stderr_of_failure, stdout_of};

fn actor(args: &[&str]) -> std::process::Output {
    run("actor", args)
}

fn json(args: &[&str]) -> Value {
    serde_json::from_str(stdout_of(&actor(args)).trim()).expect("one JSON object")
}

#[test]
fn greedy_evaluation_reports_every_field() {
    let v = json(&["eval", "--policy", "greedy", "--seeds", "0..60", "--json"]);
    assert_eq!(v["episodes"], 60);
    let rate = |k: &str| v[k].as_f64().unwrap_or_else(|| panic!("{k} missing"));
    let total = rate("success_rate") + rate("collision_rate") + rate("timeout_rate");
    assert!((total - 1.0).abs() < 1e-9, "{v}");
    // Driving straight at the target crashes more often than not at the
    // density of `docs/spec.md`.
    assert!(rate("collision_rate") > rate("success_rate"), "{v}");
    assert!(rate("success_rate") > 0.0, "{v}");
    assert!(rate("mean_steps") > 10.0 && rate("mean_steps") <= 1000.0);
    assert!(rate("mean_return").is_finite());
}

#[test]
fn evaluation_is_reproducible_and_batch_independent() {
    // Everything but the policy's time, which is measured.
    let eval = |batch| {
        let mut v = json(&["eval", "--seeds", "100..130", "--json", "--batch", batch]);
        let time = v
            .as_object_mut()
            .unwrap()
            .remove("policy_us_per_observation");
        assert!(time.unwrap().as_f64().unwrap() >= 0.0);
        v
    };
    assert_eq!(eval("7"), eval("64"));
}

#[test]
fn a_random_policy_evaluates_and_never_reaches_the_target() {
    let v = json(&["eval", "--policy", "random", "--seeds", "0..8", "--json"]);
    assert_eq!(v["episodes"], 8);
    assert_eq!(
        v["success_rate"], 0.0,
        "a random walk does not reach 1000 px: {v}"
    );
}

#[test]
fn bad_arguments_are_named() {
    let err = stderr_of_failure(&actor(&["eval", "--policy", "clever"]));
    assert!(err.contains("unknown policy `clever`"), "{err}");
    let err = stderr_of_failure(&actor(&["eval", "--seeds", "9..3"]));
    assert!(err.contains("invalid seed list"), "{err}");
    let err = stderr_of_failure(&actor(&["bench", "--seconds", "0"]));
    assert!(err.contains("--seconds"), "{err}");
}

#[test]
fn config_files_are_validated_and_applied() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "[env]\ntime_limit = 0\n").unwrap();
    let err = stderr_of_failure(&actor(&["--config", bad.to_str().unwrap(), "config"]));
    assert!(err.contains("env.time_limit"), "{err}");

    let missing = dir.path().join("missing.toml");
    let err = stderr_of_failure(&actor(&["--config", missing.to_str().unwrap(), "config"]));
    assert!(err.contains("missing.toml"), "{err}");

    let good = dir.path().join("good.toml");
    std::fs::write(
        &good,
        "[env]\ntime_limit = 40\n[env.image]\nwidth = 80\nheight = 64\n",
    )
    .unwrap();
    let path = good.to_str().unwrap();
    let printed: toml::Table =
        toml::from_str(&stdout_of(&actor(&["--config", path, "config"]))).unwrap();
    assert_eq!(printed["env"]["time_limit"].as_integer(), Some(40));
    assert_eq!(printed["env"]["stage_speed_px"].as_float(), Some(10.0));
    // A 40-step limit cannot reach a target 1000 px away at 10 px per step.
    let v = json(&["--config", path, "eval", "--seeds", "0..20", "--json"]);
    assert_eq!(v["success_rate"], 0.0, "{v}");
    assert!(v["mean_steps"].as_f64().unwrap() <= 40.0);
}

#[test]
fn demo_writes_the_pictures() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("pictures");
    let text = stdout_of(&actor(&[
        "demo",
        "--seeds",
        "0..2",
        "--out",
        out.to_str().unwrap(),
    ]));
    for name in ["fig5-seed0.png", "fig5-seed1.png", "fig6-seed0.png"] {
        let bytes = std::fs::read(out.join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(
            bytes.starts_with(b"\x89PNG\r\n\x1a\n"),
            "{name} is not a PNG"
        );
        assert!(text.contains(name), "{text}");
    }
    assert!(text.contains("success rate"), "{text}");
}
