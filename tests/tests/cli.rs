//! The operator CLI, `tweezer`, against a real learner and a real hardware
//! agent on its twin: status as JSON, a snapshot download, and the agent's
//! control (episode, emergency stop, reset); errors name what to fix.

use serde_json::Value;
use tweezer_system_tests::{
    TINY_ENV, credentials, run, start_agent, start_learner, stderr_of_failure, stdout_of, stop,
    write,
};

fn json(out: &str) -> Value {
    serde_json::from_str(out.lines().last().expect("a line of output")).unwrap()
}

/// `tweezer` with a control token.
fn tweezer(args: &[&str]) -> std::process::Output {
    let security = credentials().file("control");
    let mut all = vec!["--security", security.as_str()];
    all.extend_from_slice(args);
    run("tweezer", &all)
}

/// A learner of the tiny environment with its run directory in `dir`.
fn tiny_learner(dir: &std::path::Path) -> (std::process::Child, String) {
    let config = write(
        &dir.join("learner.toml"),
        &format!("{TINY_ENV}\n[learner]\nlisten = \"127.0.0.1:0\"\n"),
    );
    let run_dir = dir.join("run");
    start_learner(&["--config", &config, "--run-dir", run_dir.to_str().unwrap()])
}

#[test]
fn the_cli_reads_the_learner_and_drives_the_agent() {
    let dir = tempfile::tempdir().unwrap();
    let (learner, addr) = tiny_learner(dir.path());

    let status = json(&stdout_of(&tweezer(&[
        "--json",
        "learner",
        "--learner",
        &addr,
        "status",
    ])));
    assert_eq!(status["steps_inserted"], 0);
    assert!(status["buffer_capacity"].as_u64().unwrap() > 0);
    let latest = status["latest_snapshot"].as_u64().unwrap();
    assert!(latest >= 1, "{status}");
    let paused = json(&stdout_of(&tweezer(&[
        "--json",
        "learner",
        "--learner",
        &addr,
        "pause",
    ])));
    assert_eq!(paused["paused"], true);
    let written = json(&stdout_of(&tweezer(&[
        "--json",
        "learner",
        "--learner",
        &addr,
        "checkpoint",
    ])));
    let checkpoint = std::path::PathBuf::from(written["checkpoint"].as_str().unwrap());
    assert!(
        checkpoint.starts_with(dir.path().join("run")) && checkpoint.is_file(),
        "{written}"
    );
    let resumed = json(&stdout_of(&tweezer(&[
        "--json",
        "learner",
        "--learner",
        &addr,
        "resume",
    ])));
    assert_eq!(resumed["paused"], false);
    let table = stdout_of(&tweezer(&["learner", "--learner", &addr, "status"]));
    assert!(
        table.lines().any(|l| l.starts_with("limiter_state")),
        "{table}"
    );

    let listed = stdout_of(&tweezer(&[
        "--json",
        "learner",
        "--learner",
        &addr,
        "snapshots",
    ]));
    let rows: Vec<Value> = listed
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let newest = rows.last().expect("the learner keeps its first snapshot");
    assert_eq!(newest["version"].as_u64().unwrap(), latest, "{listed}");
    assert!(
        newest["tags"].as_str().unwrap().contains("latest"),
        "{listed}"
    );
    assert_eq!(newest["sha256"].as_str().unwrap().len(), 64);

    let file = dir.path().join("latest.safetensors");
    let download = json(&stdout_of(&tweezer(&[
        "--json",
        "learner",
        "--learner",
        &addr,
        "download",
        "latest",
        "--out",
        file.to_str().unwrap(),
    ])));
    assert_eq!(download["version"].as_u64().unwrap(), latest);
    assert_eq!(download["sha256"], newest["sha256"]);
    assert_eq!(
        download["size_bytes"].as_u64().unwrap(),
        std::fs::metadata(&file).unwrap().len()
    );
    let err = stderr_of_failure(&tweezer(&[
        "learner",
        "--learner",
        &addr,
        "download",
        "999",
        "-o",
        "x",
    ]));
    assert!(err.contains("not kept"), "{err}");
    assert!(stop(learner).0.success());

    let records = dir.path().join("records");
    let (mut agent, agent_addr) = start_agent(
        &["--rate", "20", "--records", records.to_str().unwrap()],
        None,
    );
    let ctl = |args: &[&str]| {
        let mut all = vec!["--json", "agent", "--agent", agent_addr.as_str()];
        all.extend_from_slice(args);
        tweezer(&all)
    };
    let status = json(&stdout_of(&ctl(&["status"])));
    assert_eq!(status["state"], "idle");
    assert_eq!(status["policy"], "greedy baseline");
    let done = json(&stdout_of(&ctl(&["start", "--twin-seed", "1", "--wait"])));
    assert_eq!(done["last_outcome"], "success", "{done}");
    assert_eq!(done["episode"], 1);
    let stopped = json(&stdout_of(&ctl(&["estop", "--reason", "cli test"])));
    assert_eq!(stopped["state"], "emergency_stopped");
    let err = stderr_of_failure(&ctl(&["start", "--target-um", "10,0"]));
    assert!(
        err.contains("emergency stop") && err.contains("not in a state"),
        "{err}"
    );
    let reset = json(&stdout_of(&ctl(&["reset"])));
    assert_eq!(reset["state"], "idle");
    let _ = agent.kill();
    let _ = agent.wait();

    // Nothing listening: the error names the address and the option.
    let err = stderr_of_failure(&tweezer(&["agent", "--agent", "127.0.0.1:1", "status"]));
    assert!(
        err.contains("the hardware agent: cannot reach https://127.0.0.1:1"),
        "{err}"
    );
    assert!(err.contains("--agent"), "{err}");
}

#[test]
fn watching_the_learner_draws_its_trends_under_the_table() {
    let dir = tempfile::tempdir().unwrap();
    let (learner, addr) = tiny_learner(dir.path());
    let security = credentials().file("read");
    let mut watch = std::process::Command::new(tweezer_system_tests::binary("tweezer"))
        .args(["--security", &security, "learner", "--learner", &addr])
        .args(["status", "--watch", "0.2"])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_secs(3));
    let _ = watch.kill();
    let out = tweezer_system_tests::output_within(
        watch,
        std::time::Duration::from_secs(30),
        "tweezer status --watch",
    );
    let text = String::from_utf8_lossy(&out.stdout);
    // Every poll prints the table, then one line per trend; the rates need
    // two polls.
    let last = text
        .rsplit("\n\n")
        .find(|poll| !poll.trim().is_empty())
        .unwrap();
    for label in [
        "rolling_return",
        "success_rate",
        "updates/s",
        "steps_inserted/s",
    ] {
        let line = last
            .lines()
            .find(|l| l.starts_with(label) && l.contains("range"))
            .unwrap_or_else(|| panic!("no {label} trend in {last}"));
        assert!(line.contains('▁'), "{line}");
    }
    assert!(stop(learner).0.success());
}
