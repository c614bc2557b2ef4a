//! `actor bench` as a process: it prints every figure as JSON.

use std::process::Command;

#[test]
fn bench_prints_its_figures() {
    let output = Command::new(env!("CARGO_BIN_EXE_actor"))
        .args(["bench", "--json", "--seconds", "0.05", "--repetitions", "1"])
        .output()
        .expect("the actor runs");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&output.stdout).expect("one JSON object");
    for key in [
        "env_steps_per_sec_1core",
        "env_steps_per_sec_all_cores",
        "render_us_median",
        "render_incremental_us_median",
    ] {
        assert!(v[key].as_f64().unwrap_or(0.0) > 0.0, "{key}: {v}");
    }
    assert_eq!(v["resolution"], serde_json::json!([320, 256]));
}
