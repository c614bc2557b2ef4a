//! A learner's run directory under faults, with real processes: a second
//! learner on a directory in use is refused, temporary files a SIGKILL
//! left are cleaned at the next start, and a full disk under the
//! checkpoints is an error the learner reports and survives.

use std::path::Path;
use std::process::Command;
use std::time::Duration;
use tonic::Code;
use tweezer_proto::pb;
use tweezer_proto::pb::learner_client::LearnerClient;
use tweezer_system_tests::{
    Running, TINY_ENV, binary, connect, credentials, run, spawn_service, start_learner,
    stderr_of_failure, write,
};

/// A learner config on the tiny environment.
fn learner_config(dir: &Path) -> String {
    write(
        &dir.join("learner.toml"),
        &format!("{TINY_ENV}\n[learner]\nlisten = \"127.0.0.1:0\"\n"),
    )
}

#[test]
fn a_second_learner_on_a_run_directory_in_use_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let config = learner_config(dir.path());
    let run_dir = dir.path().join("run");
    let run_dir = run_dir.to_str().unwrap();
    let (first, _) = start_learner(&["--config", &config, "--run-dir", run_dir]);
    let first = Running::new(first);
    for second in [
        vec!["--config", &config, "--run-dir", run_dir, "--auto-resume"],
        vec!["--resume", run_dir],
    ] {
        let security = credentials().file("server");
        let mut args = vec!["serve", "--security", &security];
        args.extend(second);
        let err = stderr_of_failure(&run("learner", &args));
        assert!(
            err.contains("in use by another learner")
                && err.contains(&first.child().id().to_string()),
            "{err}"
        );
    }
    assert!(first.stop().0.success());
    // Once the first has stopped, the run resumes.
    let (again, _) = start_learner(&["--resume", run_dir]);
    assert!(Running::new(again).stop().0.success());
}

#[test]
fn temporary_files_a_crash_left_are_removed_at_the_next_start() {
    let dir = tempfile::tempdir().unwrap();
    let config = learner_config(dir.path());
    let run_dir = dir.path().join("run");
    let (learner, _) =
        start_learner(&["--config", &config, "--run-dir", run_dir.to_str().unwrap()]);
    assert!(Running::new(learner).stop().0.success());
    // What a SIGKILL mid-write leaves: hidden temporary files beside the
    // checkpoints and snapshots.
    let leftovers = [
        run_dir.join("checkpoints/.ckpt-000000000120-000000000000.twz.tmp"),
        run_dir.join("snapshots/.v000009.safetensors.tmp"),
        run_dir.join("snapshots/.best.safetensors.link"),
        run_dir.join(".config.toml.tmp"),
    ];
    for path in &leftovers {
        std::fs::write(path, vec![7u8; 4096]).unwrap();
    }
    let kept = run_dir.join("checkpoints/notes.txt");
    std::fs::write(&kept, "an operator's file").unwrap();
    let (learner, _) = start_learner(&["--resume", run_dir.to_str().unwrap()]);
    for path in &leftovers {
        assert!(!path.exists(), "{} is still there", path.display());
    }
    assert!(kept.exists(), "only temporary files are removed");
    assert!(Running::new(learner).stop().0.success());
}

/// Whether this machine lets an unprivileged process mount a tmpfs in a
/// namespace of its own (util-linux's `unshare`, user namespaces).
fn can_mount_privately() -> bool {
    Command::new("unshare")
        .args(["-rm", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt"])
        .status()
        .is_ok_and(|s| s.success())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_under_the_checkpoints_is_reported_and_survived() {
    assert!(
        can_mount_privately(),
        "this test mounts a small tmpfs in a namespace of its own: it needs util-linux's \
         `unshare` (Debian: util-linux) and user namespaces (sysctl kernel.unprivileged_userns_clone=1)"
    );
    let dir = tempfile::tempdir().unwrap();
    let config = learner_config(dir.path());
    let run_dir = dir.path().join("run");
    let checkpoints = run_dir.join("checkpoints");
    std::fs::create_dir_all(&checkpoints).unwrap();
    let security = credentials().file("server");
    // The learner in a mount namespace of its own, its checkpoints on a
    // 64 MiB tmpfs that a filler file has filled.
    let mut command = Command::new("unshare");
    command
        .args([
            "-rm",
            "sh",
            "-c",
            "mount -t tmpfs -o size=64m tmpfs \"$1\" && \
             (dd if=/dev/zero of=\"$1/filler\" bs=4k 2>/dev/null; true) && \
             shift && exec \"$@\"",
            "sh",
        ])
        .arg(&checkpoints)
        .arg(binary("learner"))
        .args([
            "serve",
            "--security",
            &security,
            "--config",
            &config,
            "--run-dir",
        ])
        .arg(&run_dir);
    let (learner, addr) = spawn_service("learner", command, Some(&dir.path().join("learner.log")));
    let learner = Running::new(learner);
    let mut client = LearnerClient::new(connect(&addr, "control").await);

    let refused = tokio::time::timeout(
        Duration::from_secs(60),
        client.checkpoint(pb::CheckpointRequest {}),
    )
    .await
    .expect("Checkpoint answers on a full disk")
    .expect_err("no checkpoint fits");
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(refused.message().contains("No space left"), "{refused:?}");

    // Still serving.
    let before = client
        .get_status(pb::LearnerStatusRequest {})
        .await
        .expect("the learner still serves")
        .into_inner();
    // Room again: the filler goes (seen through the learner's own mounts).
    let filler = Path::new(&format!("/proc/{}/root", learner.child().id()))
        .join(checkpoints.strip_prefix("/").unwrap())
        .join("filler");
    std::fs::remove_file(&filler).unwrap();
    let written = client
        .checkpoint(pb::CheckpointRequest {})
        .await
        .expect("a checkpoint once there is room")
        .into_inner();
    assert!(written.path.contains("ckpt-"), "{written:?}");
    let after = client
        .get_status(pb::LearnerStatusRequest {})
        .await
        .unwrap()
        .into_inner();
    assert!(after.updates >= before.updates);
    let (exit, _) = learner.stop();
    assert!(exit.success(), "{exit}");
    let log = std::fs::read_to_string(dir.path().join("learner.log")).unwrap();
    assert!(log.contains("checkpoint failed"), "{log}");
}
