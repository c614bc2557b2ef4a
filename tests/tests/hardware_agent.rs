//! The hardware agent takes its policy from a live learner over gRPC,
//! verifies it, and drives the digital twin with it; snapshots that do not
//! exist or do not fit are refused with the reason.

use serde_json::Value;
use tweezer_system_tests::{
    AGENT_CONTROL, TINY_ENV, credentials, run, start_learner, stderr_of_failure, stdout_of, stop,
    write,
};

#[test]
fn the_agent_drives_the_twin_with_a_learner_snapshot_and_refuses_what_does_not_fit() {
    let dir = tempfile::tempdir().unwrap();
    let learner_config = write(
        &dir.path().join("learner.toml"),
        &format!("{TINY_ENV}\n[learner]\nlisten = \"127.0.0.1:0\"\n"),
    );
    let run_dir = dir.path().join("run");
    let (learner, addr) = start_learner(&[
        "--config",
        &learner_config,
        "--run-dir",
        run_dir.to_str().unwrap(),
    ]);
    let records = dir.path().join("records");
    let agent = |name: &str, image: [u32; 2], snapshot: &str| {
        let config = write(
            &dir.path().join(name),
            &format!(
                "[env]\nmin_free_spheres = 0\nmax_free_spheres = 0\ntime_limit = 8\n\
                 [env.image]\nwidth = {}\nheight = {}\n\
                 [policy]\nsource = \"learner\"\nlearner = \"{addr}\"\nsnapshot = {snapshot:?}\n\
                 {AGENT_CONTROL}",
                image[0], image[1]
            ),
        );
        run(
            "hardware-agent",
            &[
                "--config",
                &config,
                "--security",
                &credentials().file("read"),
                "run",
                "--twin",
                "--rate",
                "20",
                "--records",
                records.to_str().unwrap(),
            ],
        )
    };

    // The learner's first (untrained) snapshot drives the twin.
    let out = stdout_of(&agent("latest.toml", [20, 16], "latest"));
    let episode: Value = serde_json::from_str(out.lines().next().unwrap()).unwrap();
    assert_eq!(episode["summary"]["ending"], "timeout", "{episode}");
    let record = std::fs::read_to_string(episode["files"]["record"].as_str().unwrap()).unwrap();
    let header: Value = serde_json::from_str(record.lines().next().unwrap()).unwrap();
    let policy = header["header"]["policy"].as_str().unwrap();
    assert!(
        policy.starts_with(&format!("learner {addr} snapshot v")),
        "{policy}"
    );

    // A version the learner does not have, a network for other images, and
    // a learner that is gone are refused, each with its reason.
    let err = stderr_of_failure(&agent("missing.toml", [20, 16], "999"));
    assert!(
        err.contains("the v999 snapshot") && err.contains("not kept"),
        "{err}"
    );
    let err = stderr_of_failure(&agent("wider.toml", [40, 32], "latest"));
    assert!(
        err.contains("refusing the policy") && err.contains("width 20 vs 40"),
        "{err}"
    );
    assert!(stop(learner).0.success());
    let err = stderr_of_failure(&agent("gone.toml", [20, 16], "latest"));
    assert!(err.contains("cannot fetch the latest snapshot"), "{err}");
}
