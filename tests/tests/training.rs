//! Training with real processes: a learner and two actors on loopback
//! through the SIGKILL of an actor and of the learner, and the one-command
//! `experiment train` stopped by SIGINT.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use tweezer_system_tests::{
    TINY_ENV, binary, credentials, experiment_train, free_port, output_of, output_within, run,
    signal, start_learner, status, stdout_of, stop, tiny_train_file, wait_for_learner, write,
};

/// Processes killed when a test ends early.
struct Processes(Vec<Child>);

impl Drop for Processes {
    fn drop(&mut self) {
        for child in &mut self.0 {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

fn start_actor(config: &str, id: &str, seed: u64) -> Child {
    Command::new(binary("actor"))
        .args(["--config", config, "run", "--id", id])
        .args(["--security", &credentials().file("actor")])
        .args(["--seed", &seed.to_string()])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

/// The newest checkpoint's (updates, steps), from its file name.
fn newest_checkpoint(dir: &Path) -> Option<(u64, u64)> {
    std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| {
            let name = e.ok()?.file_name().into_string().ok()?;
            let counts = name.strip_prefix("ckpt-")?.strip_suffix(".twz")?;
            let (updates, steps) = counts.split_once('-')?;
            Some((updates.parse().ok()?, steps.parse().ok()?))
        })
        .max()
}

fn report(stdout: &str) -> serde_json::Value {
    serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("{e}: {stdout:?}"))
}

#[test]
fn two_actors_train_through_the_sigkill_of_an_actor_and_of_the_learner() {
    let dir = tempfile::tempdir().unwrap();
    let addr = format!("127.0.0.1:{}", free_port());
    let run_dir = dir.path().join("run");
    let learner_config = write(
        &dir.path().join("learner.toml"),
        &format!(
            "{TINY_ENV}\n[learner]\nlisten = \"{addr}\"\nuniform_steps = 500\n\
             [learner.limiter]\nmin_size = 200\nupdates_per_insert = 0.25\n\
             [learner.snapshots]\nevery_updates = 50\n\
             [learner.checkpoints]\nevery_seconds = 1\nkeep = 2\n"
        ),
    );
    let actor_config = write(
        &dir.path().join("actor.toml"),
        &format!(
            "{TINY_ENV}\n[actor]\nlearner = \"{addr}\"\nenvs = 4\nbatch_steps = 50\n\
             max_unacked = 2\nreconnect_initial_ms = 50\nreconnect_max_ms = 400\n"
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
    let mut procs = Processes(vec![
        learner,
        start_actor(&actor_config, "actor-a", 1),
        start_actor(&actor_config, "actor-b", 2),
    ]);
    let minute = Duration::from_secs(60);

    // Both stream, and the actors act with the learner's snapshots.
    wait_for_learner(
        &runtime,
        &addr,
        "two actors past exploration",
        2 * minute,
        |s| s.connected_actors == 2 && !s.explore_uniformly && s.latest_snapshot >= 3,
    );
    // The operator sees each actor.
    let security = credentials().file("read");
    let listed = stdout_of(&run(
        "tweezer",
        &[
            "--json",
            "--security",
            &security,
            "learner",
            "--learner",
            &addr,
            "actors",
        ],
    ));
    let actors: Vec<serde_json::Value> = listed
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let ids: Vec<&str> = actors.iter().map(|a| a["id"].as_str().unwrap()).collect();
    assert_eq!(ids, ["actor-a", "actor-b"], "{listed}");
    for actor in &actors {
        assert_eq!(actor["streams"], 1, "{listed}");
        assert!(actor["steps"].as_u64().unwrap() > 0, "{listed}");
        assert!(actor["idle_seconds"].as_f64().unwrap() < 30.0, "{listed}");
    }

    // SIGKILL of one actor: the learner trains on; the actor, restarted
    // under its id, rejoins and its steps are stored again.
    procs.0[2].kill().unwrap();
    procs.0[2].wait().unwrap();
    let alone = wait_for_learner(&runtime, &addr, "the learner noticing", minute, |s| {
        s.connected_actors == 1
    });
    wait_for_learner(&runtime, &addr, "training on with one actor", minute, |s| {
        s.updates >= alone.updates + 50
    });
    procs.0[2] = start_actor(&actor_config, "actor-b", 3);
    let rejoined = wait_for_learner(&runtime, &addr, "the actor rejoining", minute, |s| {
        s.connected_actors == 2
    });
    wait_for_learner(&runtime, &addr, "the rejoined actor's steps", minute, |s| {
        s.steps_inserted >= rejoined.steps_inserted + 400
    });

    // SIGKILL of the learner: resumed from its newest checkpoint, it starts
    // from the checkpointed counts and the actors come back by themselves.
    let checkpoints = run_dir.join("checkpoints");
    let deadline = Instant::now() + minute;
    while newest_checkpoint(&checkpoints).is_none_or(|(updates, _)| updates == 0) {
        assert!(Instant::now() < deadline, "no periodic checkpoint");
        std::thread::sleep(Duration::from_millis(100));
    }
    procs.0[0].kill().unwrap();
    procs.0[0].wait().unwrap();
    let (updates, steps) = newest_checkpoint(&checkpoints).unwrap();
    procs.0[0] = start_learner(&["--resume", run_dir.to_str().unwrap()]).0;
    // The actors may already be back with a few batches.
    let resumed = status(&runtime, &addr).unwrap();
    assert!(
        resumed.updates >= updates
            && resumed.updates < updates + 100
            && resumed.steps_inserted >= steps
            && resumed.steps_inserted < steps + 2_000,
        "resumed from the newest checkpoint ({updates} updates, {steps} steps): {resumed:?}"
    );
    wait_for_learner(
        &runtime,
        &addr,
        "training continuing with both actors",
        2 * minute,
        |s| {
            s.connected_actors == 2
                && s.updates >= updates + 100
                && s.latest_snapshot > resumed.latest_snapshot
        },
    );

    let learner = procs.0.remove(0);
    let mut reports = Vec::new();
    for actor in procs.0.drain(..) {
        let (exit, stdout) = stop(actor);
        assert!(exit.success());
        reports.push(report(&stdout));
    }
    for r in &reports {
        assert!(r["steps_acked"].as_u64().unwrap() > 0, "{r}");
        assert!(r["reconnects"].as_u64().unwrap() >= 1, "{r}");
        let versions = r["snapshots_loaded"].as_array().unwrap();
        assert!(
            versions.len() >= 2,
            "snapshots propagate to each actor: {r}"
        );
    }
    assert!(stop(learner).0.success());
}

#[test]
fn sigint_stops_a_one_command_run_with_a_loadable_final_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let train = write(
        &dir.path().join("train.toml"),
        &tiny_train_file(
            "[learner.checkpoints]\nevery_seconds = 0\n\
             [train]\nactors = 2\nminutes = 0\neval_seeds = \"0..8\"\npicture_seeds = \"0..1\"\n",
        ),
    );
    let child = experiment_train(&train, &out)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut procs = Processes(vec![child]);
    let deadline = Instant::now() + Duration::from_secs(120);
    while !out.join("snapshots/v000003.safetensors").exists() {
        assert!(Instant::now() < deadline, "the run never published v3");
        std::thread::sleep(Duration::from_millis(100));
    }
    signal(&procs.0[0], "INT");
    let output = output_within(
        procs.0.remove(0),
        Duration::from_secs(180),
        "the interrupted run",
    );
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let outcome = report(&String::from_utf8(output.stdout).unwrap());
    let summary = &outcome["runs"][0];
    assert_eq!(summary["interrupted"], true, "{outcome}");
    assert!(summary["updates"].as_u64().unwrap() > 0, "{outcome}");
    let rows = outcome["report"]["rows"].as_array().unwrap();
    let policies: Vec<&str> = rows.iter().map(|r| r["policy"].as_str().unwrap()).collect();
    assert_eq!(
        policies[1..],
        ["greedy", "planner"],
        "the best snapshot, greedy and the planner: {summary}"
    );
    for file in [
        "train.toml",
        "config.toml",
        "actor.toml",
        "security/learner.toml",
        "security/read.toml",
        "security/read.token",
        "report/eval.md",
        "report/eval.json",
    ] {
        assert!(out.join(file).is_file(), "{file}");
    }
    // The evaluated snapshot is kept under a name that stays put.
    let evaluated = std::fs::read(rows[0]["snapshot"].as_str().unwrap()).unwrap();
    let chosen = out.join("snapshots/chosen.safetensors");
    assert_eq!(std::fs::read(&chosen).unwrap(), evaluated);
    let files = outcome["report"]["files"].as_array().unwrap();
    assert!(
        files.iter().any(|f| f == chosen.to_str().unwrap()),
        "{outcome}"
    );

    // The final checkpoint loads: a resumed learner has every update.
    let (updates, steps) = newest_checkpoint(&out.join("checkpoints")).expect("a final checkpoint");
    assert!(updates >= summary["updates"].as_u64().unwrap(), "{outcome}");
    let (learner, addr) =
        start_learner(&["--listen", "127.0.0.1:0", "--resume", out.to_str().unwrap()]);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let resumed = status(&runtime, &addr).unwrap();
    assert_eq!((resumed.updates, resumed.steps_inserted), (updates, steps));
    assert!(stop(learner).0.success());
}

#[test]
fn a_sweep_trains_each_run_in_turn_and_reports_them_together() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sweep");
    let train = write(
        &dir.path().join("sweep.toml"),
        &tiny_train_file(
            "[train]\nminutes = 0.15\neval_seeds = \"0..4\"\npicture_seeds = \"0\"\n\
             [sweep]\nseeds = [1, 2]\ngamma = [0.8]\n",
        ),
    );
    let output = output_of(&mut experiment_train(&train, &out));
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let outcome = report(&String::from_utf8(output.stdout).unwrap());
    let runs = outcome["runs"].as_array().unwrap();
    assert_eq!(runs.len(), 2, "{outcome}");
    for (run, seed) in runs.iter().zip([1, 2]) {
        let run_dir = out.join(format!("gamma0.8-seed{seed}"));
        assert_eq!(run["run_dir"], run_dir.to_str().unwrap(), "{outcome}");
        assert!(run["updates"].as_u64().unwrap() > 0, "{outcome}");
        assert!(newest_checkpoint(&run_dir.join("checkpoints")).is_some());
        let file = std::fs::read_to_string(run_dir.join("train.toml")).unwrap();
        assert!(file.contains("gamma = 0.8") && file.contains(&format!("seed = {seed}")));
    }
    let rows = outcome["report"]["rows"].as_array().unwrap();
    let policies: Vec<&str> = rows.iter().map(|r| r["policy"].as_str().unwrap()).collect();
    assert_eq!(
        policies.len(),
        4,
        "two best snapshots, greedy and the planner: {policies:?}"
    );
    assert_eq!(policies[2..], ["greedy", "planner"]);
    let fig4 = std::fs::read_to_string(out.join("report/fig4-reward.svg")).unwrap();
    assert!(fig4.contains("gamma 0.8 (2 runs)"), "the runs are averaged");
}

/// `--updates` ends a run once its learner has made exactly that many,
/// long before its minutes, with a snapshot at that many to report.
#[test]
fn updates_end_a_run_at_exactly_that_many() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let train = write(
        &dir.path().join("train.toml"),
        &tiny_train_file("[train]\nminutes = 30\neval_seeds = \"0..4\"\npicture_seeds = \"0\"\n"),
    );
    let output = output_of(experiment_train(&train, &out).args(["--updates", "120"]));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    assert!(
        stderr.contains("the learner made its max_updates"),
        "{stderr}"
    );
    let outcome = report(&String::from_utf8(output.stdout).unwrap());
    let run = &outcome["runs"][0];
    assert_eq!(run["updates"], 120, "{outcome}");
    assert_eq!(run["interrupted"], false, "{outcome}");
    let file = std::fs::read_to_string(out.join("config.toml")).unwrap();
    assert!(file.contains("max_updates = 120"), "{file}");
    // Snapshots every 50 updates, and one at exactly 120.
    let versions: Vec<String> = std::fs::read_dir(out.join("snapshots"))
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    assert!(
        versions.iter().any(|v| v == "v000004.safetensors"),
        "{versions:?}"
    );
    assert!(
        !versions.iter().any(|v| v == "v000005.safetensors"),
        "{versions:?}"
    );
}

/// (success, return) of `snapshot` on `seeds` by `actor eval`, checked by
/// its critics or its actor alone.
fn validation_score(actor_config: &Path, snapshot: &Path, seeds: &str, alone: bool) -> (f64, f64) {
    let (config, snapshot) = (actor_config.to_str().unwrap(), snapshot.to_str().unwrap());
    let mut args = vec!["eval", "--config", config, "--policy", snapshot];
    args.extend(["--seeds", seeds, "--json"]);
    if alone {
        args.push("--actor-alone");
    }
    let summary = report(&stdout_of(&run("actor", &args)));
    let figure = |name: &str| summary[name].as_f64().unwrap();
    (figure("success_rate"), figure("mean_return"))
}

/// A set network's run is reported as it acts, its critics checking its
/// actor where that did better on the validation seeds, and the other way
/// beside it; the microscope's copy holds the critics only where their
/// check was kept. Of every kept snapshot, each acting both ways, none does
/// better on the validation seeds than the one chosen, as it was chosen.
#[test]
fn a_set_run_is_reported_with_and_without_its_critics_check() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let train = write(
        &dir.path().join("train.toml"),
        &tiny_train_file(
            "[learner.network]\nkind = \"set\"\n\
             [train]\nminutes = 30\neval_seeds = \"0..4\"\nvalidation_seeds = \"10..14\"\n\
             picture_seeds = \"0\"\n",
        ),
    );
    let output = output_of(experiment_train(&train, &out).args(["--updates", "120"]));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    let outcome = report(&String::from_utf8(output.stdout).unwrap());
    let rows = outcome["report"]["rows"].as_array().unwrap();
    let policies: Vec<&str> = rows.iter().map(|r| r["policy"].as_str().unwrap()).collect();
    let how = rows[0]["chosen_by"].as_str().unwrap();
    let kept = how.contains("critics' check kept");
    assert!(kept || how.contains("critics' check dropped"), "{how}");
    let other = match kept {
        true => format!("{} actor alone", policies[0]),
        false => format!("{} checked by its critics", policies[0]),
    };
    assert_eq!(
        policies[1..],
        [other.as_str(), "greedy", "planner"],
        "{outcome}"
    );
    let chosen = std::fs::read(out.join("snapshots/chosen.safetensors")).unwrap();
    // The tiny environment keeps the default field of view, all a set
    // network needs of it.
    let env = tweezer_gym::EnvConfig::default();
    let (policy, _) =
        tweezer_nets::NetworkPolicy::from_snapshot(&chosen, &env, &burn::tensor::Device::flex())
            .unwrap();
    assert_eq!(policy.has_critics(), kept, "{how}");

    let (config, seeds) = (out.join("actor.toml"), "10..14");
    let chosen = validation_score(
        &config,
        &out.join("snapshots/chosen.safetensors"),
        seeds,
        !kept,
    );
    let mut candidates = 0;
    for entry in std::fs::read_dir(out.join("snapshots")).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_str().unwrap();
        if !(name.starts_with('v') || name == "best.safetensors") {
            continue;
        }
        candidates += 1;
        for alone in [false, true] {
            let score = validation_score(&config, &path, seeds, alone);
            assert!(
                score <= chosen,
                "{name} (alone: {alone}) {score:?} beats {how}: {chosen:?}"
            );
        }
    }
    assert!(candidates >= 2, "{candidates} candidates: {how}");
}
