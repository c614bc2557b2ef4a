//! TensorBoard reads what the learner writes, with its own event reader
//! (PyPI's `tensorboard`, in a fresh venv): scalars equal to
//! `metrics.jsonl` while the learner runs and after it is SIGKILLed, and a
//! one-command sweep that TensorBoard lists run by run, each with its
//! held-out evaluation.

use std::path::Path;
use std::process::Command;
use std::time::Duration;
use tweezer_system_tests::{
    Running, TINY_ENV, binary, check, credentials, experiment_train, output_of, python_venv,
    signal, start_learner, stdout_of, tiny_train_file, wait_for_learner, write,
};

fn json(text: &str) -> serde_json::Value {
    serde_json::from_str(text.trim()).unwrap_or_else(|e| panic!("{e}: {text}"))
}

/// Checks the run in `run_dir` with TensorBoard's reader: every number of
/// every line of `metrics.jsonl` is a scalar of the same step and value.
fn check_run(python: &Path, script: &str, run_dir: &Path) -> serde_json::Value {
    let report = json(&check(python, &[script, "run", run_dir.to_str().unwrap()]));
    assert_eq!(report["mismatches"], serde_json::json!([]), "{report}");
    report
}

#[test]
fn tensorboard_reads_the_learners_scalars_live_after_a_sigkill_and_across_a_sweep() {
    let dir = tempfile::tempdir().unwrap();
    let bin = python_venv(dir.path(), "requirements-tensorboard.txt");
    let python = bin.join("python");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("python/tensorboard_check.py");
    let script = script.to_str().unwrap();

    // A learner and an actor: the scalars are there while it runs.
    let run_dir = dir.path().join("run");
    let config = write(
        &dir.path().join("learner.toml"),
        &format!(
            "{TINY_ENV}[learner]\nlisten = \"127.0.0.1:0\"\nuniform_steps = 300\n\
             metrics_every_updates = 20\n\
             [learner.limiter]\nmin_size = 200\nupdates_per_insert = 0.25\n\
             [learner.snapshots]\nevery_updates = 50\n[learner.checkpoints]\nevery_seconds = 0\n"
        ),
    );
    let (learner, addr) =
        start_learner(&["--config", &config, "--run-dir", run_dir.to_str().unwrap()]);
    let learner = Running::new(learner);
    let actor = write(
        &dir.path().join("actor.toml"),
        &format!("{TINY_ENV}[actor]\nlearner = \"{addr}\"\nenvs = 4\nbatch_steps = 50\n"),
    );
    stdout_of(&output_of(
        Command::new(binary("actor"))
            .args(["--config", &actor, "run", "--steps", "1500"])
            .args(["--security", &credentials().file("actor")]),
    ));
    // The steps are in; the learner trains on them and logs as it goes.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let minutes = Duration::from_secs(180);
    wait_for_learner(&runtime, &addr, "200 updates", minutes, |s| {
        s.updates >= 200
    });
    let live = check_run(&python, script, &run_dir);
    let tags = live["tags"].as_array().unwrap();
    for tag in [
        "update/critic_loss",
        "update/actor_loss",
        "update/mean_q",
        "update/updates_per_sec",
        "update/insert_rate",
        "update/replay_fill",
        "episode/episode_return",
        "episode/success",
        "snapshot/version",
        "snapshot/rolling_success_rate",
    ] {
        assert!(tags.iter().any(|t| t == tag), "no {tag} in {live}");
    }
    assert!(live["compared"].as_u64().unwrap() > 100, "{live}");

    // SIGKILL: the file holds whole records, all of them readable.
    signal(learner.child(), "KILL");
    drop(learner);
    let killed = check_run(&python, script, &run_dir);
    assert!(killed["compared"].as_u64().unwrap() >= live["compared"].as_u64().unwrap());

    // A sweep of two runs: `--logdir` lists each, with its evaluation.
    let out = dir.path().join("sweep");
    let train = write(
        &dir.path().join("sweep.toml"),
        &tiny_train_file(
            "[train]\nminutes = 0.15\neval_seeds = \"0..4\"\npicture_seeds = \"0\"\n\
             [sweep]\nseeds = [1, 2]\n",
        ),
    );
    let trained = output_of(&mut experiment_train(&train, &out));
    let outcome = json(&stdout_of(&trained));
    let listed = json(&check(&python, &[script, "logdir", out.to_str().unwrap()]));
    let runs = listed.as_object().unwrap();
    assert_eq!(runs.len(), 2, "{listed}");
    for (row, seed) in outcome["report"]["rows"].as_array().unwrap()[..2]
        .iter()
        .zip([1, 2])
    {
        let name = format!("seed{seed}");
        let tags = runs[&name].as_array().unwrap();
        for tag in [
            "update/critic_loss",
            "train/updates_per_sec",
            "eval/success_rate",
        ] {
            assert!(
                tags.iter().any(|t| t == tag),
                "{name}: no {tag} in {listed}"
            );
        }
        let report = check_run(&python, script, &out.join(&name));
        assert!(report["lines"].as_u64().unwrap() > 0);
        let log = std::fs::read_to_string(out.join(&name).join("metrics.jsonl")).unwrap();
        let eval = log
            .lines()
            .map(json)
            .find(|l| l["kind"] == "eval")
            .expect("an eval line");
        assert_eq!(eval["success_rate"], row["success_rate"], "{eval} vs {row}");
    }
}
