//! The Python policy package (`python/`, installed from its own
//! `pyproject.toml` into a fresh venv) loads snapshots of both
//! architectures trained by a short real run (a learner and an actor over
//! gRPC; the set network reads motion, also turned towards the goal, or
//! reads and acts in the goal frame among faster spheres, whose motion unit
//! its snapshot records), and its
//! actions for unseen observations match the Rust policy's actor alone
//! (`actor act --actor-alone`) to
//! 1e-4; it refuses a snapshot whose weights were altered.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;
use tweezer_system_tests::{
    Running, binary, check, credentials, output_of, python_venv, run, start_learner, stdout_of,
    wait_for_learner, write,
};

/// SPEC's environment (free spheres in view) with short episodes, and the
/// quick preset's 40 x 32 images for the CNN.
const ENV: &str = "[env]\ntime_limit = 200\n[env.image]\nwidth = 40\nheight = 32\n";

/// A learner that learns from the first few hundred steps and publishes
/// often.
const LEARNER: &str = "[learner]\nlisten = \"127.0.0.1:0\"\nuniform_steps = 400\n\
    [learner.limiter]\nmin_size = 200\nupdates_per_insert = 0.25\n\
    [learner.snapshots]\nevery_updates = 40\nkeep = 50\n[learner.checkpoints]\nevery_seconds = 0\n";

/// Trains `network` (a `[learner.network]` table) for 1,600 steps of one
/// actor in `env` (an `[env]` table); returns the first snapshot
/// (untrained) and the newest.
fn snapshots(dir: &Path, env: &str, network: &str) -> [PathBuf; 2] {
    let config = write(
        &dir.join("learner.toml"),
        &format!("{env}{LEARNER}{network}"),
    );
    let run_dir = dir.join("run");
    let (learner, addr) =
        start_learner(&["--config", &config, "--run-dir", run_dir.to_str().unwrap()]);
    let learner = Running::new(learner);
    let actor_config = write(
        &dir.join("actor.toml"),
        &format!("{env}[actor]\nlearner = \"{addr}\"\nenvs = 4\nbatch_steps = 100\n"),
    );
    let streamed = output_of(
        Command::new(binary("actor"))
            .args(["--config", &actor_config, "run", "--steps", "1600"])
            .args(["--security", &credentials().file("actor")]),
    );
    stdout_of(&streamed);
    // The steps are in; the learner trains on them until it publishes.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let minutes = Duration::from_secs(180);
    wait_for_learner(&runtime, &addr, "a trained snapshot", minutes, |s| {
        s.latest_snapshot >= 2
    });
    let (exit, _) = learner.stop();
    assert!(exit.success());
    let mut versions: Vec<PathBuf> = std::fs::read_dir(run_dir.join("snapshots"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.file_name().unwrap().to_str().unwrap().starts_with('v'))
        .collect();
    versions.sort();
    let first = run_dir.join("snapshots/v000001.safetensors");
    let newest = versions.pop().expect("published snapshots");
    assert!(newest != first, "no snapshot after training: {newest:?}");
    [first, newest]
}

/// Copies the files of `from` (recursively) into a new directory `to`.
fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let path = entry.unwrap().path();
        let target = to.join(path.file_name().unwrap());
        if path.is_dir() {
            copy_dir(&path, &target);
        } else {
            std::fs::copy(&path, &target).unwrap();
        }
    }
}

#[test]
fn python_loads_trained_snapshots_of_both_architectures_and_acts_as_rust_does() {
    let dir = tempfile::tempdir().unwrap();
    let bin = python_venv(dir.path(), "requirements-policy.txt");
    let here = Path::new(env!("CARGO_MANIFEST_DIR"));
    // pip builds in the source tree: build a copy, not the repository.
    let package = dir.path().join("python");
    copy_dir(&here.join("../python"), &package);
    check(
        &bin.join("python"),
        &[
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            "--no-deps",
            package.to_str().unwrap(),
        ],
    );
    let script = here.join("python/policy_check.py");
    let script = script.to_str().unwrap();
    let python = bin.join("python");
    // The goal-frame network learns among faster spheres, so its snapshot
    // records a motion unit of its own.
    let faster = ENV.replace("[env]\n", "[env]\nmax_sphere_speed_px = 5.0\n");

    for (name, env, network) in [
        ("paper", ENV, ""),
        (
            "set",
            ENV,
            "[learner.network]\nkind = \"set\"\nsphere_hidden = 32\ninputs = \"goal\"\n",
        ),
        (
            "set-goal-frame",
            faster.as_str(),
            "[learner.network]\nkind = \"set\"\nsphere_hidden = 32\ninputs = \"motion\"\n\
             frame = \"goal\"\n",
        ),
    ] {
        let work = dir.path().join(name);
        std::fs::create_dir(&work).unwrap();
        let env_file = write(&work.join("env.toml"), env);
        let observations = work.join("observations.jsonl");
        let observations = observations.to_str().unwrap();
        check(
            &python,
            &[
                script,
                "observations",
                observations,
                "--fov",
                "1280",
                "1024",
                "--seed",
                "7",
            ],
        );
        let architecture = if name.starts_with("set") {
            "tweezer-set-actor-v1"
        } else {
            "tweezer-paper-actor-v1"
        };
        let mut unsaturated = 0;
        let [first, newest] = snapshots(&work, env, network);
        for snapshot in [&first, &newest] {
            let snapshot = snapshot.to_str().unwrap();
            let actions = stdout_of(&run(
                "actor",
                &[
                    "--config",
                    &env_file,
                    "act",
                    "--actor-alone",
                    "--policy",
                    snapshot,
                    "--observations",
                    observations,
                ],
            ));
            let rust = write(&work.join("rust.jsonl"), &actions);
            let report = check(
                &python,
                &[
                    script,
                    "compare",
                    snapshot,
                    observations,
                    &rust,
                    "--fov",
                    "1280",
                    "1024",
                ],
            );
            let report: serde_json::Value = serde_json::from_str(report.trim()).unwrap();
            assert_eq!(report["actions"], 200, "{name}: {report}");
            assert!(
                report["numpy"].as_f64().unwrap() <= 1e-4,
                "{name}: {report}"
            );
            assert!(
                report["torch"] == "not installed" || report["torch"].as_f64().unwrap() <= 1e-4,
                "{name}: {report}"
            );
            assert_eq!(report["architecture"], architecture);
            match name {
                "set" => {
                    assert_eq!(report["inputs"], "goal", "{report}");
                    assert_eq!(report["motion_unit_px"], 2.0, "{report}");
                }
                "set-goal-frame" => {
                    assert_eq!(report["frame"], "goal", "{report}");
                    assert_eq!(report["motion_unit_px"], 5.0, "{report}");
                }
                _ => {}
            }
            unsaturated += report["unsaturated"].as_u64().unwrap();
        }
        // Most actions are inside (-1, 1), where any difference would show.
        assert!(
            unsaturated >= 200,
            "{name}: {unsaturated} of 800 components unsaturated"
        );
        let snapshot = newest.to_str().unwrap();

        // One weight changed in the file: both sides refuse it.
        let mut bytes = std::fs::read(snapshot).unwrap();
        let last = bytes.len() - 1;
        bytes[last] ^= 0x40;
        let altered = work.join("altered.safetensors");
        std::fs::write(&altered, bytes).unwrap();
        let altered = altered.to_str().unwrap();
        let refused = output_of(Command::new(&python).args([
            "-c",
            "import sys, tweezer_policy; tweezer_policy.load(sys.argv[1])",
            altered,
        ]));
        let err = String::from_utf8_lossy(&refused.stderr);
        assert!(
            !refused.status.success(),
            "{name}: Python loaded an altered snapshot"
        );
        assert!(err.contains("fail their checksum"), "{name}: {err}");
        let refused = run(
            "actor",
            &[
                "--config",
                &env_file,
                "act",
                "--policy",
                altered,
                "--observations",
                observations,
            ],
        );
        assert!(
            !refused.status.success(),
            "{name}: Rust loaded an altered snapshot"
        );
    }
}
