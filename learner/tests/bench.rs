//! `learner bench` on a small configuration: every figure is measured.

use tweezer_learner::bench::LearnerBench;
use tweezer_learner::config::{DeviceChoice, NetworkConfig, SetNetworkConfig};

#[test]
fn the_bench_measures_every_figure_of_a_small_configuration() {
    let env = tweezer_gym::EnvConfig {
        image: tweezer_gym::ImageConfig {
            width: 80,
            height: 64,
        },
        ..tweezer_gym::EnvConfig::default()
    };
    let paper = NetworkConfig::Paper;
    let set = NetworkConfig::Set(SetNetworkConfig::default());
    for network in [paper, set] {
        let report =
            tweezer_learner::bench::run(&env, &network, 32, 2_000, 2, DeviceChoice::Flex).unwrap();
        check(&report);
        let name = network.architecture(&env).name();
        assert!(report.architecture.starts_with(name), "{report:?}");
        assert_eq!(report.device, "flex", "{report:?}");
    }
}

fn check(report: &LearnerBench) {
    assert_eq!(report.updates_timed, 2);
    for v in [
        report.update_ms_mean,
        report.critic_step_ms,
        report.actor_step_ms,
        report.actor_infer_ms_batch1,
        report.actor_infer_ms_batch16,
    ] {
        assert!(v > 0.0 && v.is_finite(), "{report:?}");
    }
    assert!(
        report.replay_bytes_per_transition > 40.0 && report.replay_bytes_per_transition < 500.0
    );
    assert!(report.ingest_transitions_per_sec > 0.0);
}
