//! Helpers for the system tests, which start the workspace's binaries as
//! real processes.

use std::path::PathBuf;
use std::process::{Command, Output};

/// The path of binary `bin` of package `package`, built with the profile the
/// tests were built with (cargo's build is a no-op when it is fresh).
pub fn binary(package: &str, bin: &str) -> PathBuf {
    escargot::CargoBuild::new()
        .package(package)
        .bin(bin)
        .current_release()
        .current_target()
        .run()
        .unwrap_or_else(|e| panic!("cannot build {bin}: {e}"))
        .path()
        .to_path_buf()
}

/// Runs `bin` of `package` with `args` to completion.
pub fn run(package: &str, bin: &str, args: &[&str]) -> Output {
    Command::new(binary(package, bin))
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
