//! `learner bench` on a small configuration: every figure is measured.

use tweezer_gym::{EnvConfig, ImageConfig};
use tweezer_learner::bench::{LearnerBench, run};
use tweezer_learner::config::{LearnerConfig, NetworkConfig, SetNetworkConfig};
use tweezer_learner::training::td3::Td3Config;

fn small() -> EnvConfig {
    EnvConfig {
        image: ImageConfig {
            width: 80,
            height: 64,
        },
        ..EnvConfig::default()
    }
}

#[test]
fn the_bench_measures_every_figure_of_a_small_configuration() {
    let env = small();
    let paper = NetworkConfig::Paper;
    let set = NetworkConfig::Set(SetNetworkConfig::default());
    for network in [paper, set] {
        let learner = LearnerConfig {
            network: network.clone(),
            batch_size: 32,
            ..LearnerConfig::default()
        };
        let report = run(&env, &learner, 2_000, 2).unwrap();
        check(&report);
        let name = network.architecture(&env).name();
        assert!(report.architecture.starts_with(name), "{report:?}");
        assert_eq!(report.device, "flex", "{report:?}");
    }
}

#[test]
fn the_bench_trains_with_the_configured_td3() {
    let learner = LearnerConfig {
        td3: Td3Config {
            policy_delay: 0,
            ..Td3Config::default()
        },
        ..LearnerConfig::default()
    };
    let error = run(&small(), &learner, 100, 2).unwrap_err();
    assert!(
        format!("{error:#}").contains("td3.policy_delay"),
        "{error:#}"
    );
}

fn check(report: &LearnerBench) {
    assert_eq!(report.updates_timed, 2);
    assert_eq!(report.batch_size, 32);
    for v in [
        report.update_ms_mean,
        report.critic_step_ms,
        report.actor_step_ms,
        report.actor_infer_ms_batch1,
        report.actor_infer_ms_batch16,
    ] {
        assert!(v > 0.0 && v.is_finite(), "{report:?}");
    }
    // A replay of 2,000 transitions is mostly its deques' growth slack.
    assert!(
        report.replay_bytes_per_transition > 40.0 && report.replay_bytes_per_transition < 600.0,
        "{report:?}"
    );
    assert!(report.ingest_transitions_per_sec > 0.0);
}
