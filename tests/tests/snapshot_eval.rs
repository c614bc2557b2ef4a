//! `actor eval` runs a policy snapshot file, and refuses one that does not
//! fit the configured resolution, naming the config that fits it.

use burn::tensor::Device;
use tweezer_nets::{ActorConfig, Architecture, EncoderConfig, SnapshotInfo, encode};
use tweezer_system_tests::{run, stderr_of_failure, stdout_of};

#[test]
fn snapshots_are_evaluated_and_mismatches_refused() {
    let dir = tempfile::tempdir().unwrap();
    let actor = ActorConfig::new(EncoderConfig::new(64, 80)).init(&Device::flex());
    let info = SnapshotInfo {
        architecture: Architecture::Paper {
            height: 64,
            width: 80,
        },
        version: 1,
        training_step: 0,
    };
    let snapshot = dir.path().join("untrained.safetensors");
    std::fs::write(&snapshot, encode(&actor, &info)).unwrap();
    let config = dir.path().join("small.toml");
    std::fs::write(
        &config,
        "[env]\ntime_limit = 60\n[env.image]\nwidth = 80\nheight = 64\n",
    )
    .unwrap();
    let (snapshot, config) = (snapshot.to_str().unwrap(), config.to_str().unwrap());

    let out = stdout_of(&run(
        "actor",
        &[
            "--config", config, "eval", "--policy", snapshot, "--seeds", "0..6", "--json",
        ],
    ));
    let v: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(v["episodes"], 6);
    assert!(v["mean_steps"].as_f64().unwrap() <= 60.0);

    // The default 320 x 256 resolution does not fit an 80 x 64 network.
    let err = stderr_of_failure(&run(
        "actor",
        &["eval", "--policy", snapshot, "--seeds", "0..2"],
    ));
    assert!(
        err.contains("height 64 vs 256") && err.contains("width 80 vs 320"),
        "{err}"
    );
    assert!(err.contains("--config RUN/actor.toml"), "{err}");
    // In a run directory, the hint names that run's config.
    let run_dir = dir.path().join("run");
    std::fs::create_dir_all(run_dir.join("snapshots")).unwrap();
    let in_run = run_dir.join("snapshots/v000001.safetensors");
    std::fs::copy(snapshot, &in_run).unwrap();
    let err = stderr_of_failure(&run(
        "actor",
        &[
            "eval",
            "--policy",
            in_run.to_str().unwrap(),
            "--seeds",
            "0..2",
        ],
    ));
    let hint = format!("--config {}/actor.toml", run_dir.display());
    assert!(err.contains(&hint), "{err}");

    let garbage = dir.path().join("garbage.safetensors");
    std::fs::write(&garbage, b"not a snapshot at all").unwrap();
    let err = stderr_of_failure(&run(
        "actor",
        &["eval", "--policy", garbage.to_str().unwrap()],
    ));
    assert!(err.contains("not a safetensors snapshot"), "{err}");
}
