//! The hardware agent follows a training run: with `LoadPolicy { latest,
//! follow }` it picks up each newer snapshot a live learner publishes as
//! an actor streams to it, between episodes on its twin and never during
//! one; status, telemetry and episode records name the version that drove
//! each episode; loading another policy ends following. A learner the
//! agent cannot reach is named as the agent's, not the operator's, problem.

use std::collections::{BTreeMap, BTreeSet};
use std::process::Command;
use std::time::{Duration, Instant};
use tweezer_proto::pb;
use tweezer_proto::pb::hardware_agent_client::HardwareAgentClient;
use tweezer_system_tests::{
    AGENT_CONTROL, Running, agent_state, binary, connect, credentials, free_port, learner_status,
    output_of, run, start_configured_agent, start_learner, stderr_of_failure, wait_for_agent,
    write,
};

/// A small set network that publishes often.
const LEARNER: &str = "[env]\ntime_limit = 60\n[learner]\nlisten = \"127.0.0.1:0\"\n\
    uniform_steps = 300\n[learner.network]\nkind = \"set\"\nsphere_hidden = 16\nhead_hidden = 16\n\
    [learner.limiter]\nmin_size = 200\nupdates_per_insert = 0.25\n\
    [learner.snapshots]\nevery_updates = 20\nkeep = 50\n[learner.checkpoints]\nevery_seconds = 0\n";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_agent_follows_a_live_learner_between_episodes() {
    let dir = tempfile::tempdir().unwrap();
    let config = write(&dir.path().join("learner.toml"), LEARNER);
    let run = dir.path().join("run");
    let (learner, learner_addr) =
        start_learner(&["--config", &config, "--run-dir", run.to_str().unwrap()]);
    let learner = Running::new(learner);
    let actor_config = write(
        &dir.path().join("actor.toml"),
        &format!(
            "[env]\ntime_limit = 60\n[actor]\nlearner = \"{learner_addr}\"\nenvs = 4\nbatch_steps = 50\n"
        ),
    );
    // Training in bursts between episodes: the twin's real-time loop never
    // shares the two cores with a busy learner.
    let train = |steps: &str| {
        let streamed = output_of(
            Command::new(binary("actor"))
                .args(["--config", &actor_config, "run", "--steps", steps])
                .args(["--security", &credentials().file("actor")]),
        );
        assert!(
            streamed.status.success(),
            "{}",
            String::from_utf8_lossy(&streamed.stderr)
        );
    };
    train("400");

    let agent_config = write(
        &dir.path().join("agent.toml"),
        &format!(
            "{AGENT_CONTROL}[env]\ntime_limit = 60\n[policy]\nlearner = \"{learner_addr}\"\nsnapshot = \"latest\"\ntimeout_s = 10.0\n"
        ),
    );
    let records = dir.path().join("records");
    let (agent, addr) = start_configured_agent(
        &agent_config,
        &["--rate", "10", "--records", records.to_str().unwrap()],
        None,
    );
    let agent = Running::new(agent);
    let mut client = HardwareAgentClient::new(connect(&addr, "control").await);
    let load = |snapshot: &str, follow| pb::LoadPolicyRequest {
        source: Some(pb::load_policy_request::Source::LearnerSnapshot(
            snapshot.into(),
        )),
        follow,
    };

    // A version cannot be followed; a tag can.
    let refused = client.load_policy(load("1", true)).await.unwrap_err();
    assert_eq!(refused.code(), tonic::Code::InvalidArgument, "{refused:?}");
    let loaded = client
        .load_policy(load("latest", true))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(loaded.following, "latest");
    let mut telemetry = client
        .stream_telemetry(pb::TelemetryRequest {})
        .await
        .unwrap()
        .into_inner();

    // Episodes on the twin, with a burst of training before each, until
    // three versions have driven them.
    let mut driven: Vec<(u64, u64)> = Vec::new(); // (episode, version)
    let deadline = Instant::now() + Duration::from_secs(240);
    while driven.iter().map(|d| d.1).collect::<BTreeSet<_>>().len() < 3 {
        assert!(
            Instant::now() < deadline,
            "the agent did not pick up new snapshots: {driven:?}"
        );
        let before = learner_status(&learner_addr, "read")
            .await
            .unwrap()
            .latest_snapshot;
        train("200");
        // Until the learner has published and, caught up, idles.
        loop {
            let status = learner_status(&learner_addr, "read").await.unwrap();
            if status.latest_snapshot > before && status.limiter_state == "waiting for data" {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "the learner never caught up: {status:?}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        // The follower asks every 2 s.
        tokio::time::sleep(Duration::from_millis(2500)).await;
        client
            .start_episode(pb::StartEpisodeRequest {
                target: None,
                twin_seed: Some(100_000 + driven.len() as u64),
            })
            .await
            .unwrap();
        let ended = wait_for_agent(
            &mut client,
            "the end of a new episode",
            deadline.saturating_duration_since(Instant::now()),
            |status| {
                status.episode as usize > driven.len()
                    && agent_state(status) != pb::AgentState::Running
            },
        )
        .await;
        assert_eq!(ended.state, pb::AgentState::Idle as i32, "{ended:?}");
        assert_eq!(ended.following, "latest");
        driven.push((ended.episode, ended.policy_version));
    }
    let versions: Vec<u64> = driven.iter().map(|d| d.1).collect();
    assert!(
        versions.windows(2).all(|w| w[0] <= w[1]),
        "versions only move forward: {versions:?}"
    );

    // Every telemetry message of an episode names the version its record
    // names, one version per episode.
    let mut seen: BTreeMap<u64, BTreeSet<u64>> = Default::default();
    while let Ok(Ok(Some(message))) =
        tokio::time::timeout(Duration::from_millis(200), telemetry.message()).await
    {
        seen.entry(message.episode)
            .or_default()
            .insert(message.policy_version);
    }
    for (episode, version) in &driven {
        let record = records.join(format!("episode-{episode:06}.jsonl"));
        let first = std::fs::read_to_string(&record).unwrap();
        let header: serde_json::Value =
            serde_json::from_str(first.lines().next().unwrap()).unwrap();
        assert_eq!(header["header"]["policy_version"], *version, "{header}");
        if let Some(versions) = seen.get(episode) {
            assert_eq!(versions.len(), 1, "episode {episode}: {versions:?}");
            assert!(
                versions.contains(version),
                "episode {episode}: {versions:?} vs {version}"
            );
        }
    }

    // Loading anything else ends following.
    let greedy = client
        .load_policy(pb::LoadPolicyRequest {
            source: Some(pb::load_policy_request::Source::Greedy(true)),
            follow: false,
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(greedy.following, "");
    assert_eq!(greedy.policy_version, 0);
    drop(agent);
    let (exit, _) = learner.stop();
    assert!(exit.success());
}

/// With the learner down, `tweezer agent load --follow best` blames the
/// agent's `[policy] learner`, not the agent's address or the request;
/// with the agent down, it points at the agent's address.
#[test]
fn a_learner_the_agent_cannot_reach_is_named_as_such() {
    let dir = tempfile::tempdir().unwrap();
    let nobody = format!("127.0.0.1:{}", free_port());
    let agent_config = write(
        &dir.path().join("agent.toml"),
        &format!("{AGENT_CONTROL}[policy]\nlearner = \"{nobody}\"\ntimeout_s = 2.0\n"),
    );
    let (agent, addr) = start_configured_agent(&agent_config, &[], None);
    let agent = Running::new(agent);
    let control = credentials().file("control");
    let load = |at: &str| {
        run(
            "tweezer",
            &[
                "--security",
                &control,
                "agent",
                "--agent",
                at,
                "load",
                "--follow",
                "best",
            ],
        )
    };
    let err = stderr_of_failure(&load(&addr));
    assert!(
        err.contains(&format!("learner at {nobody}"))
            && err.contains("policy.learner")
            && err.contains("cannot reach what it needs"),
        "{err}"
    );
    assert!(!err.contains("malformed"), "{err}");
    drop(agent);

    let err = stderr_of_failure(&load(&nobody));
    assert!(err.contains("check the address"), "{err}");
}
