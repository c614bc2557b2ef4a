//! Helpers for the system tests, which start the workspace's binaries as
//! real processes.

use serde_json::Value;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

/// Every binary of the workspace by name, built once per test process by
/// `cargo build --workspace --all-targets`: the same targets, and so the
/// same feature resolution, as `cargo test --workspace`, which makes the
/// build a no-op there instead of a second build of every dependency.
fn binaries() -> &'static HashMap<String, PathBuf> {
    static BINARIES: OnceLock<HashMap<String, PathBuf>> = OnceLock::new();
    BINARIES.get_or_init(|| {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let manifest = Path::new(env!("CARGO_MANIFEST_DIR")).join("../Cargo.toml");
        let output = Command::new(cargo)
            .args([
                "build",
                "--workspace",
                "--all-targets",
                "--message-format=json",
            ])
            .arg("--manifest-path")
            .arg(manifest)
            .output()
            .expect("cargo runs");
        assert!(
            output.status.success(),
            "cargo build failed:\n{}",
            String::from_utf8_lossy(&output.stderr)
        );
        String::from_utf8_lossy(&output.stdout)
            .lines()
            .filter_map(|line| serde_json::from_str::<Value>(line).ok())
            .filter(|m| m["reason"] == "compiler-artifact" && m["profile"]["test"] == false)
            .filter(|m| {
                m["target"]["kind"]
                    .as_array()
                    .is_some_and(|k| k.iter().any(|k| k == "bin"))
            })
            .filter_map(|m| {
                let name = m["target"]["name"].as_str()?.to_string();
                let path = PathBuf::from(m["executable"].as_str()?);
                Some((name, path))
            })
            .collect()
    })
}

/// The path of the workspace binary `bin`.
pub fn binary(bin: &str) -> &'static Path {
    binaries()
        .get(bin)
        .unwrap_or_else(|| panic!("the workspace has no binary `{bin}`"))
}

/// Runs binary `bin` with `args` to completion.
pub fn run(bin: &str, args: &[&str]) -> Output {
    Command::new(binary(bin))
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("cannot start {bin}: {e}"))
}

/// Standard output of a run that must succeed.
pub fn stdout_of(output: &Output) -> String {
    assert!(
        output.status.success(),
        "exit {:?}\nstderr: {}",
        output.status,
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout.clone()).expect("utf-8 output")
}

/// Standard error of a run that must fail.
pub fn stderr_of_failure(output: &Output) -> String {
    assert!(!output.status.success(), "expected failure, got success");
    String::from_utf8_lossy(&output.stderr).into_owned()
}
