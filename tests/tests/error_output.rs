//! Every binary reports a user's mistake the same way: `error: ` and what
//! is wrong, each cause said once, exit status 1, and no backtrace, even
//! with `RUST_BACKTRACE=1` (a mistake is not a crash).

use std::process::Command;
use tweezer_system_tests::{binary, output_of, write};

/// Runs `bin` with `args` and checks that it fails plainly, saying `says`.
fn fails_plainly(bin: &str, args: &[&str], says: &str) {
    let output = output_of(
        Command::new(binary(bin))
            .args(args)
            .env("RUST_BACKTRACE", "1")
            .env("RUST_LOG", "off"),
    );
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{bin} {args:?}: {stderr}");
    assert!(stderr.starts_with("error: "), "{bin} {args:?}: {stderr}");
    assert_eq!(stderr.matches(says).count(), 1, "{bin} {args:?}: {stderr}");
    for noise in ["backtrace", "Caused by", "Error:"] {
        assert!(!stderr.contains(noise), "{bin} {args:?}: {stderr}");
    }
}

#[test]
fn a_missing_file_is_one_plain_message_from_every_binary() {
    let missing = "/nonexistent/tweezer.toml";
    for bin in ["actor", "learner", "hardware-agent"] {
        fails_plainly(
            bin,
            &["--config", missing, "config"],
            "cannot read config file /nonexistent/tweezer.toml",
        );
    }
    fails_plainly(
        "experiment",
        &["train", "--config", missing, "--print-config"],
        "cannot read config file /nonexistent/tweezer.toml",
    );
    fails_plainly(
        "tweezer",
        &["--security", missing, "learner", "status"],
        "security file /nonexistent/tweezer.toml",
    );
}

#[test]
fn a_bad_field_is_named_once() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("agent.toml");
    std::fs::write(&file, "[camera]\nsource = \"webcam\"\n").unwrap();
    fails_plainly(
        "hardware-agent",
        &["--config", file.to_str().unwrap(), "config"],
        "unknown variant `webcam`",
    );
}

#[test]
fn report_refuses_a_config_it_would_ignore() {
    fails_plainly(
        "experiment",
        &["--config", "nonexist.toml", "report", "runs/x"],
        "--config nonexist.toml does not apply",
    );
}

#[test]
fn actor_eval_says_what_is_wrong_with_its_policy_and_batch() {
    let dir = tempfile::tempdir().unwrap();
    let dir_name = dir.path().to_str().unwrap();
    fails_plainly(
        "actor",
        &["eval", "--policy", dir_name, "--seeds", "0..1"],
        "is a directory",
    );
    fails_plainly(
        "actor",
        &[
            "eval",
            "--policy",
            "runs/x/snapshots/best.safetensors",
            "--seeds",
            "0..1",
        ],
        "policy file runs/x/snapshots/best.safetensors does not exist",
    );
    fails_plainly(
        "actor",
        &["eval", "--policy", "gredy", "--seeds", "0..1"],
        "unknown policy `gredy`",
    );
    // Argument errors are clap's: status 2, the flag named.
    let output = output_of(Command::new(binary("actor")).args(["eval", "--batch", "0"]));
    assert_eq!(output.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&output.stderr).contains("--batch"));
}

#[test]
fn a_flag_out_of_range_is_blamed_on_the_flag() {
    fails_plainly(
        "experiment",
        &["train", "--minutes", "-1", "--print-config"],
        "--minutes:",
    );
    fails_plainly(
        "experiment",
        &["train", "--actors", "100000", "--print-config"],
        "--actors:",
    );
}

#[test]
fn a_token_is_never_written_over_an_existing_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("reader.token");
    std::fs::write(&out, "keep me\n").unwrap();
    let tokens = dir.path().join("tokens");
    fails_plainly(
        "tweezer",
        &[
            "token",
            "new",
            "--role",
            "read",
            "--name",
            "reader",
            "--tokens",
            tokens.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        "already exists, and a secret is never overwritten",
    );
    assert_eq!(std::fs::read_to_string(&out).unwrap(), "keep me\n");
}

#[test]
fn a_bad_field_is_blamed_on_the_field_the_user_set() {
    let dir = tempfile::tempdir().unwrap();
    let file = |name: &str, text: &str| write(&dir.path().join(name), text);
    let pooling = file(
        "pooling.toml",
        "[learner.network]\nkind = \"set\"\npooling = \"sum\"\n",
    );
    fails_plainly(
        "learner",
        &["--config", &pooling, "config"],
        "learner.network.pooling: unknown variant `sum`",
    );
    let stages = file("stages.toml", "[stages]\nmax_speed_mm_s = 5.0\n");
    fails_plainly(
        "hardware-agent",
        &["--config", &stages, "config"],
        "`stages.max_speed_mm_s`: 5 must lie in [0.0001, 2.6]",
    );
    let optics = file("optics.toml", "[twin.optics]\nfocus = 3.0\n");
    fails_plainly(
        "hardware-agent",
        &["--config", &optics, "config"],
        "`twin.optics.focus`",
    );
    let fov = file("fov.toml", "[env]\nfov_px = [1280, 1000]\n");
    for bin in ["learner", "actor"] {
        fails_plainly(bin, &["--config", &fov, "config"], "`env.fov_px`");
    }
    // The train file's [actor] table is checked before anything starts.
    let train = file("train.toml", "[actor]\nenvz = 4\n");
    let out = dir.path().join("run");
    fails_plainly(
        "experiment",
        &["train", "--config", &train, "--out", out.to_str().unwrap()],
        "unknown field `envz`",
    );
    assert!(!out.exists(), "no run directory is made");
}

#[test]
fn resuming_what_is_not_a_run_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let nodir = dir.path().join("nodir");
    fails_plainly(
        "learner",
        &["serve", "--resume", nodir.to_str().unwrap()],
        "is not a run directory",
    );
}

#[test]
fn a_missing_token_file_is_blamed_on_the_security_file() {
    let dir = tempfile::tempdir().unwrap();
    let security = dir.path().join("client.toml");
    std::fs::write(&security, "plaintext = true\ntoken_file = \"gone.token\"\n").unwrap();
    fails_plainly(
        "tweezer",
        &[
            "--security",
            security.to_str().unwrap(),
            "learner",
            "--learner",
            "127.0.0.1:9",
            "status",
        ],
        "`token_file` names",
    );
}
