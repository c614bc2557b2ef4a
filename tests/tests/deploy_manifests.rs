//! The Kubernetes manifests: every overlay renders with kustomize
//! (`kubectl kustomize`, from PyPI's kubectl wheel) and passes strict
//! validation against the Kubernetes 1.37 schemas (`kubernetes-validate`,
//! offline); the configuration files it ships are accepted by the
//! processes themselves.

use std::path::Path;
use tweezer_system_tests::{check, python_venv, run, stderr_of_failure, stdout_of};

#[test]
fn every_overlay_renders_validates_and_configures_the_processes() {
    let dir = tempfile::tempdir().unwrap();
    let here = Path::new(env!("CARGO_MANIFEST_DIR"));
    let bin = python_venv(dir.path(), "requirements-k8s.txt");
    let overlays = here.join("../deploy/k8s/overlays");
    let mut names: Vec<String> = std::fs::read_dir(&overlays)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, ["cpu", "gpu"]);
    for name in &names {
        let rendered = check(
            &bin.join("kubectl"),
            &["kustomize", overlays.join(name).to_str().unwrap()],
        );
        let file = dir.path().join(format!("{name}.yaml"));
        std::fs::write(&file, &rendered).unwrap();
        let validated = check(
            &bin.join("kubernetes-validate"),
            &["--strict", "-k", "1.37.0", file.to_str().unwrap()],
        );
        for kind in ["configmap", "service", "statefulset", "deployment"] {
            assert!(
                validated.contains(&format!("passed for resource {kind}/")),
                "{name}: no {kind} passed:\n{validated}"
            );
        }
        assert!(rendered.contains("- --auto-resume"), "{name}");
        assert!(rendered.contains("- $(POD_NAME)"), "{name}");

        // The shipped config files are the processes' own to judge.
        let files = dir.path().join(format!("{name}-config"));
        std::fs::create_dir(&files).unwrap();
        let listed = check(
            &bin.join("python"),
            &[
                here.join("python/configmap_files.py").to_str().unwrap(),
                file.to_str().unwrap(),
                files.to_str().unwrap(),
            ],
        );
        assert_eq!(listed.lines().count(), 5, "{name}: {listed}");
        let config = |file: &str| files.join(file).to_str().unwrap().to_string();
        if name == "gpu" {
            assert!(rendered.contains("nvidia.com/gpu: 1"), "{rendered}");
            assert!(
                rendered.contains("value: compute,utility,graphics"),
                "NVIDIA's Vulkan driver needs the graphics capability:\n{rendered}"
            );
            // The tests' learner is built with wgpu: the GPU config opens
            // it (lavapipe in CI, where TWEEZER_REQUIRE_WGPU=1), and a
            // machine without a Vulkan driver refuses it for that alone.
            let checked = run("learner", &["--config", &config("learner.toml"), "config"]);
            if !checked.status.success() && std::env::var("TWEEZER_REQUIRE_WGPU").is_err() {
                let err = stderr_of_failure(&checked);
                assert!(
                    err.contains("learner.device") && err.contains("no adapter"),
                    "{err}"
                );
                let text = std::fs::read_to_string(files.join("learner.toml")).unwrap();
                std::fs::write(
                    files.join("learner.toml"),
                    text.replace("\"wgpu\"", "\"flex\""),
                )
                .unwrap();
            } else {
                assert!(stdout_of(&checked).contains("device = \"wgpu\""));
            }
        }
        let learner = stdout_of(&run(
            "learner",
            &["--config", &config("learner.toml"), "config"],
        ));
        assert!(learner.contains("listen = \"0.0.0.0:50051\""), "{learner}");
        let actor = stdout_of(&run(
            "actor",
            &["--config", &config("actor.toml"), "config"],
        ));
        assert!(actor.contains("seed_from_id = true"), "{actor}");
        for security in ["learner-security.toml", "actor-security.toml", "probe.toml"] {
            tweezer_rpc::Security::load(Some(&files.join(security)))
                .unwrap_or_else(|e| panic!("{name}: {e}"));
        }
    }
}
