//! Where motion decides a collision, the set network that sees each
//! sphere's displacement learns to dodge better than the one that sees
//! only where the spheres are: two one-command runs of the `lean` preset's
//! network (a learner and an actor process each, over gRPC), alike but for
//! `inputs`, in a small field of fast spheres that keep their velocity,
//! judged on held-out seeds after the same number of updates.

use std::process::Stdio;
use std::time::Duration;
use tweezer_system_tests::{experiment_train, output_within, run, stdout_of, write};

/// A 640 × 512 field with about four free spheres in view, each crossing
/// it at up to 15 px a step per axis (the stage's 10 at full speed) in a
/// straight line, and a target 300 px away: greedy succeeds on about 0.41
/// of the held-out seeds, the planner on all of them, and the planner with
/// every sphere taken as standing still on 0.56. Motion is what separates
/// them.
const FAST_SPHERES: &str = r#"
fov_px = [640, 512]
world_px = [2560.0, 2048.0]
min_free_spheres = 100
max_free_spheres = 140
brownian_accel_px = 0.0
max_sphere_speed_px = 15.0
target_distance_px = 300.0
time_limit = 100

[image]
width = 20
height = 16
"#;

/// Updates each run makes: where, measured with release builds, the
/// network with motion reached 0.70–0.83 held out and the one without
/// 0.43–0.61, motion ahead by 0.17 or more on each of eight learner seeds
/// (`docs/training.md`, "Where motion should matter most").
const UPDATES: u64 = 10_000;

/// The lean preset with the environment above, `inputs` as given, smaller
/// batches, a shorter uniform start and snapshots every 500 updates, so
/// that a run is short.
fn train_file(inputs: &str) -> String {
    let preset = stdout_of(&run("experiment", &["train", "--print-config"]));
    let mut file: toml::Table = toml::from_str(&preset).unwrap();
    file.insert("env".into(), toml::from_str(FAST_SPHERES).unwrap());
    let learner = file["learner"].as_table_mut().unwrap();
    learner.insert("batch_size".into(), 128.into());
    learner.insert("uniform_steps".into(), 2000.into());
    let network = learner["network"].as_table_mut().unwrap();
    assert_eq!(network["kind"].as_str(), Some("set"), "{preset}");
    network.insert("inputs".into(), inputs.into());
    let snapshots = learner["snapshots"].as_table_mut().unwrap();
    snapshots.insert("every_updates".into(), 500.into());
    file.to_string()
}

/// The success rate of a run's reported policy (its chosen snapshot as it
/// acts) and of greedy, on the held-out seeds.
fn successes(report: &serde_json::Value) -> (f64, f64) {
    let rows = report["report"]["rows"].as_array().unwrap();
    let of = |k: usize| rows[k]["success_rate"].as_f64().unwrap();
    let greedy = rows.iter().position(|r| r["policy"] == "greedy").unwrap();
    (of(0), of(greedy))
}

#[test]
fn the_set_network_that_sees_motion_dodges_fast_spheres_better() {
    let dir = tempfile::tempdir().unwrap();
    // Both runs at once, each on about half the machine: a run ends at its
    // updates, whatever its speed.
    let runs: Vec<_> = ["positions", "motion"]
        .into_iter()
        .map(|inputs| {
            let train = write(
                &dir.path().join(format!("{inputs}.toml")),
                &train_file(inputs),
            );
            let child = experiment_train(&train, &dir.path().join(inputs))
                .args(["--updates", &UPDATES.to_string()])
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap();
            (inputs, child)
        })
        .collect();
    let [positions, motion] = runs
        .into_iter()
        .map(|(inputs, child)| {
            let limit = Duration::from_secs(40 * 60);
            let output = output_within(child, limit, &format!("the {inputs} run"));
            let stdout = String::from_utf8_lossy(&output.stdout);
            assert!(
                output.status.success(),
                "{inputs}: {}",
                String::from_utf8_lossy(&output.stderr)
            );
            let report: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
            assert_eq!(report["runs"][0]["updates"], UPDATES, "{report}");
            successes(&report)
        })
        .collect::<Vec<_>>()
        .try_into()
        .unwrap();
    let (seen, greedy) = motion;
    let (unseen, _) = positions;
    eprintln!("held out: with motion {seen}, positions alone {unseen}, greedy {greedy}");
    assert!(
        seen >= unseen + 0.1,
        "with motion {seen}, positions alone {unseen} (greedy {greedy})"
    );
}
