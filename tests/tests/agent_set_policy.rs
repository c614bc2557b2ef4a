//! The hardware agent drives its digital twin with a set-network snapshot
//! fetched from a live learner over gRPC: the same `LoadPolicy` as the
//! CNN's, no rendering on either side, a field of view wider than the one
//! it was trained on, and an episode on the twin to its end.

use std::time::Duration;
use tweezer_proto::pb;
use tweezer_proto::pb::hardware_agent_client::HardwareAgentClient;
use tweezer_system_tests::{
    AGENT_CONTROL, Running, agent_state, connect, learner_status, start_configured_agent,
    start_learner, wait_for_agent, write,
};

/// A learner of the set network on SPEC's environment.
const LEARNER: &str = r#"
[learner]
listen = "127.0.0.1:0"
[learner.network]
kind = "set"
sphere_hidden = 32
[learner.checkpoints]
every_seconds = 0
"#;

/// The augmented environment's wider field of view (virtual obstacles
/// beyond the camera's 1280 x 1024), and episodes of at most 100 steps:
/// the network trained on SPEC's field sees more centres at the scale it
/// learned.
const WIDER: &str = "[env]\nfov_px = [1600, 1280]\ntime_limit = 100\n";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_agent_drives_the_twin_with_a_set_snapshot_from_a_live_learner() {
    let dir = tempfile::tempdir().unwrap();
    let config = write(&dir.path().join("learner.toml"), LEARNER);
    let run = dir.path().join("run");
    let (learner, learner_addr) =
        start_learner(&["--config", &config, "--run-dir", run.to_str().unwrap()]);
    let learner = Running::new(learner);
    let published = learner_status(&learner_addr, "read").await.unwrap();
    assert!(published.latest_snapshot >= 1, "{published:?}");

    let agent_config = write(
        &dir.path().join("agent.toml"),
        &format!(
            "{AGENT_CONTROL}{WIDER}[policy]\nlearner = \"{learner_addr}\"\nsnapshot = \"latest\"\ntimeout_s = 10.0\n"
        ),
    );
    let records = dir.path().join("records");
    let (agent, addr) = start_configured_agent(
        &agent_config,
        &["--rate", "50", "--records", records.to_str().unwrap()],
        None,
    );
    let agent = Running::new(agent);
    let mut client = HardwareAgentClient::new(connect(&addr, "control").await);
    let loaded = client
        .load_policy(pb::LoadPolicyRequest {
            source: Some(pb::load_policy_request::Source::LearnerSnapshot(
                "latest".into(),
            )),
            follow: false,
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(loaded.policy_version, published.latest_snapshot);
    assert!(
        loaded.policy.contains("tweezer-set-actor-v1"),
        "{}",
        loaded.policy
    );

    client
        .start_episode(pb::StartEpisodeRequest {
            target: None,
            twin_seed: Some(100_000),
        })
        .await
        .unwrap();
    let ended = wait_for_agent(
        &mut client,
        "idle after episode 1",
        Duration::from_secs(60),
        |status| status.episode >= 1 && agent_state(status) == pb::AgentState::Idle,
    )
    .await;
    assert!(ended.step > 0, "{ended:?}");
    assert_eq!(ended.policy_version, published.latest_snapshot);

    // The episode's record names the set network's snapshot.
    let record = std::fs::read_dir(&records)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "jsonl"))
        .expect("an episode record");
    let text = std::fs::read_to_string(&record).unwrap();
    assert!(text.contains("tweezer-set-actor-v1"), "{text:.400}");
    drop(agent);
    let (exit, _) = learner.stop();
    assert!(exit.success());
}
