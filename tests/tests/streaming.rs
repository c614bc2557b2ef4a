//! An actor process streams to a learner process over real gRPC, loads the
//! learner's snapshots once uniform exploration ends, and carries on
//! through a learner restart without losing or repeating a step.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use tweezer_system_tests::{
    TINY_ENV, binary, credentials, free_port, output_of, output_within, start_learner, status,
    stop, write,
};

#[test]
fn an_actor_streams_through_a_learner_restart_without_losing_or_repeating_steps() {
    let dir = tempfile::tempdir().unwrap();
    let addr = format!("127.0.0.1:{}", free_port());
    let run_dir = dir.path().join("run");
    let learner_config = write(
        &dir.path().join("learner.toml"),
        &format!(
            "{TINY_ENV}\n[learner]\nlisten = \"{addr}\"\nuniform_steps = 1000\n\
             [learner.limiter]\nmin_size = 200\nupdates_per_insert = 0.25\n\
             [learner.snapshots]\nevery_updates = 100\n\
             [learner.checkpoints]\nevery_seconds = 0\nreplay = true\n"
        ),
    );
    let actor_config = write(
        &dir.path().join("actor.toml"),
        &format!(
            "{TINY_ENV}\n[actor]\nlearner = \"{addr}\"\nid = \"streaming-test\"\n\
             envs = 4\nbatch_steps = 100\nmax_unacked = 2\n\
             reconnect_initial_ms = 50\nreconnect_max_ms = 400\n"
        ),
    );
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();

    let (learner, _) = start_learner(&[
        "--config",
        &learner_config,
        "--run-dir",
        run_dir.to_str().unwrap(),
    ]);
    let actor = Command::new(binary("actor"))
        .args(["--config", &actor_config, "run", "--steps", "6000"])
        .args(["--security", &credentials().file("actor")])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();

    // Once some steps are in, the learner stops (checkpointing) and comes back.
    let deadline = Instant::now() + Duration::from_secs(120);
    while status(&runtime, &addr).is_none_or(|s| s.steps_inserted < 2_000) {
        assert!(Instant::now() < deadline, "the actor's steps never arrived");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(stop(learner).0.success());
    std::thread::sleep(Duration::from_millis(300));
    let (learner, _) = start_learner(&["--resume", run_dir.to_str().unwrap()]);

    let output = output_within(actor, Duration::from_secs(240), "the actor");
    assert!(
        output.status.success(),
        "actor failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(report["steps_acked"], 6000, "{report}");
    assert!(report["reconnects"].as_u64().unwrap() >= 1, "{report}");
    assert!(report["episodes"].as_u64().unwrap() > 0, "{report}");
    assert!(
        !report["snapshots_loaded"].as_array().unwrap().is_empty(),
        "the actor never loaded a snapshot after uniform exploration: {report}"
    );

    let learned = status(&runtime, &addr).unwrap();
    assert_eq!(
        learned.steps_inserted, 6000,
        "every acknowledged step stored exactly once: {learned:?}"
    );
    assert!(!learned.explore_uniformly);
    assert!(learned.updates > 0);
    assert!(stop(learner).0.success());
}

/// A legitimate dense field (200 spheres nearly all in view) with 4,096
/// steps a batch: batches of several MiB. The learner takes 1 MiB messages;
/// the actor learns that when it connects and splits its batches to fit.
#[test]
fn an_actor_splits_dense_batches_to_the_learners_message_limit() {
    let dir = tempfile::tempdir().unwrap();
    let addr = format!("127.0.0.1:{}", free_port());
    let env = "[env]\nworld_px = [1400.0, 1200.0]\nmin_free_spheres = 200\n\
               max_free_spheres = 200\n[env.image]\nwidth = 20\nheight = 16\n";
    let learner_config = write(
        &dir.path().join("learner.toml"),
        &format!(
            "{env}\n[learner]\nlisten = \"{addr}\"\nmax_message_bytes = 1048576\n\
             [learner.limiter]\nupdates_per_insert = 0.0001\n\
             [learner.checkpoints]\nevery_seconds = 0\n"
        ),
    );
    let actor_config = write(
        &dir.path().join("actor.toml"),
        &format!(
            "{env}\n[actor]\nlearner = \"{addr}\"\nid = \"dense\"\n\
             envs = 16\nbatch_steps = 4096\nmax_unacked = 2\n"
        ),
    );
    let (learner, _) = start_learner(&[
        "--config",
        &learner_config,
        "--run-dir",
        dir.path().join("run").to_str().unwrap(),
    ]);
    let output = output_of(
        Command::new(binary("actor"))
            .args(["--config", &actor_config, "run", "--steps", "8192"])
            .args(["--security", &credentials().file("actor")]),
    );
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "actor failed: {stderr}");
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(report["steps_acked"], 8192, "{report}");
    assert_eq!(report["reconnects"], 0, "{report}\n{stderr}");
    assert!(
        report["batches_sent"].as_u64().unwrap() > 8,
        "8,192 dense steps fit in two 1 MiB messages? {report}"
    );
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let stored = status(&runtime, &addr).unwrap();
    assert_eq!(
        (stored.steps_inserted, stored.malformed_batches),
        (8192, 0),
        "{stored:?}"
    );
    assert!(stop(learner).0.success());
}
