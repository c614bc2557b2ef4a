//! The hardware agent's states under RPCs that interleave: an emergency
//! stop during a policy load stays in force and can be reset; a load from
//! a learner that never answers ends within `policy.timeout_s`; a policy
//! "file" that would block (a FIFO) is refused; and random sequences of
//! every RPC keep the model's rules.

use std::time::{Duration, Instant};
use tonic::Code;
use tweezer_gym::SplitMix64;
use tweezer_proto::pb;
use tweezer_proto::pb::hardware_agent_client::HardwareAgentClient;
use tweezer_rpc::AuthChannel;
use tweezer_system_tests::{
    AGENT_CONTROL, Running, agent_state, agent_status, connect, start_configured_agent,
    wait_for_agent_state, write,
};

type Client = HardwareAgentClient<AuthChannel>;

/// How long the daemon may take to reach a state it was asked for.
const SETTLE: Duration = Duration::from_secs(10);

/// A daemon on the twin whose `[policy]` learner is `learner`, fetched
/// within 2 s (killed when the test ends), and its address.
fn start(dir: &std::path::Path, learner: &str) -> (Running, String) {
    let config = write(
        &dir.join("agent.toml"),
        &format!("{AGENT_CONTROL}[policy]\nlearner = \"{learner}\"\ntimeout_s = 2.0\n"),
    );
    let records = dir.join("records");
    let (child, addr) = start_configured_agent(
        &config,
        &["--rate", "20", "--records", records.to_str().unwrap()],
        None,
    );
    (Running::new(child), addr)
}

fn from_learner() -> pb::LoadPolicyRequest {
    pb::LoadPolicyRequest {
        source: Some(pb::load_policy_request::Source::LearnerSnapshot(
            "latest".into(),
        )),
        follow: false,
    }
}

fn greedy() -> pb::LoadPolicyRequest {
    pb::LoadPolicyRequest {
        source: Some(pb::load_policy_request::Source::Greedy(true)),
        follow: false,
    }
}

fn seeded(seed: u64) -> pb::StartEpisodeRequest {
    pb::StartEpisodeRequest {
        target: None,
        twin_seed: Some(seed),
    }
}

fn estop() -> pb::EmergencyStopRequest {
    pb::EmergencyStopRequest {
        reason: "test".into(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_emergency_stop_during_a_load_from_a_silent_learner_stays_and_resets() {
    // Accepts TCP connections (the kernel's backlog does) and never says a
    // word, not even the TLS handshake.
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (_daemon, addr) = start(dir.path(), &silent.local_addr().unwrap().to_string());
    let mut client = Client::new(connect(&addr, "control").await);
    wait_for_agent_state(&mut client, pb::AgentState::Idle, SETTLE).await;

    let started = Instant::now();
    let mut loader = client.clone();
    let load = tokio::spawn(async move { loader.load_policy(from_learner()).await });
    wait_for_agent_state(&mut client, pb::AgentState::Loading, SETTLE).await;
    let stopped = client.emergency_stop(estop()).await.unwrap().into_inner();
    assert_eq!(agent_state(&stopped), pb::AgentState::EmergencyStopped);

    let refused = load.await.unwrap().unwrap_err();
    let waited = started.elapsed();
    assert!(waited < Duration::from_secs(8), "the load took {waited:?}");
    assert!(
        refused.message().contains("no snapshot within 2.0 s"),
        "{refused:?}"
    );
    // The load's end did not undo the stop.
    assert_eq!(
        agent_state(&agent_status(&mut client).await),
        pb::AgentState::EmergencyStopped
    );
    let err = client.start_episode(seeded(1)).await.unwrap_err();
    assert_eq!(err.code(), Code::FailedPrecondition);
    assert!(err.message().contains("emergency stop"), "{err:?}");

    // Reset, and the agent works again.
    let reset = client
        .reset_emergency_stop(pb::ResetEmergencyStopRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(agent_state(&reset), pb::AgentState::Idle);
    client.start_episode(seeded(1)).await.unwrap();
    client
        .stop_episode(pb::StopEpisodeRequest {})
        .await
        .unwrap();

    // A FIFO would block a reader until a writer comes: refused at once.
    let fifo = dir.path().join("policy.fifo");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap();
    assert!(made.success());
    wait_for_agent_state(&mut client, pb::AgentState::Idle, SETTLE).await;
    let err = client
        .load_policy(pb::LoadPolicyRequest {
            source: Some(pb::load_policy_request::Source::File(
                fifo.to_str().unwrap().into(),
            )),
            follow: false,
        })
        .await
        .unwrap_err();
    assert!(err.message().contains("not a regular file"), "{err:?}");
    assert_eq!(
        agent_state(&agent_status(&mut client).await),
        pb::AgentState::Idle
    );
}

/// One RPC of a random sequence.
#[derive(Clone, Copy, Debug)]
enum Call {
    Start,
    Stop,
    EmergencyStop,
    Reset,
    LoadGreedy,
    /// From the silent learner, not awaited: the agent stays LOADING for
    /// up to 2 s while later calls arrive.
    LoadSilent,
    SetOverlay,
}

const CALLS: [Call; 7] = [
    Call::Start,
    Call::Stop,
    Call::EmergencyStop,
    Call::Reset,
    Call::LoadGreedy,
    Call::LoadSilent,
    Call::SetOverlay,
];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn random_sequences_of_rpcs_never_lose_an_emergency_stop_and_always_reset() {
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (_daemon, addr) = start(dir.path(), &silent.local_addr().unwrap().to_string());
    let mut client = Client::new(connect(&addr, "control").await);
    wait_for_agent_state(&mut client, pb::AgentState::Idle, SETTLE).await;

    let mut rng = SplitMix64::new(0x57a7e);
    let mut background = Vec::new();
    // Whether an emergency stop is in force in the model: from its answer
    // until a reset's.
    let mut latched = false;
    let mut trace = Vec::new();
    for i in 0..60 {
        let call = CALLS[rng.integer_inclusive(0, CALLS.len() as u32 - 1) as usize];
        trace.push(call);
        let refused_while_latched = |result: Result<(), tonic::Status>| match result {
            Err(e) => assert_eq!(e.code(), Code::FailedPrecondition, "{trace:?}: {e:?}"),
            Ok(()) => panic!("{trace:?}: accepted while an emergency stop was in force"),
        };
        match call {
            Call::Start => {
                let result = client.start_episode(seeded(i)).await.map(|_| ());
                if latched {
                    refused_while_latched(result);
                } else if let Err(e) = result {
                    assert_eq!(e.code(), Code::FailedPrecondition, "{trace:?}: {e:?}");
                }
            }
            Call::Stop => {
                client
                    .stop_episode(pb::StopEpisodeRequest {})
                    .await
                    .unwrap();
            }
            Call::EmergencyStop => {
                let s = client.emergency_stop(estop()).await.unwrap().into_inner();
                assert_eq!(
                    agent_state(&s),
                    pb::AgentState::EmergencyStopped,
                    "{trace:?}"
                );
                latched = true;
            }
            Call::Reset => {
                match client
                    .reset_emergency_stop(pb::ResetEmergencyStopRequest {})
                    .await
                {
                    Ok(_) => latched = false,
                    // Only while an episode is still ending.
                    Err(e) => assert_eq!(e.code(), Code::FailedPrecondition, "{trace:?}: {e:?}"),
                }
            }
            Call::LoadGreedy => {
                let result = client.load_policy(greedy()).await.map(|_| ());
                if latched {
                    refused_while_latched(result);
                } else if let Err(e) = result {
                    assert_eq!(e.code(), Code::FailedPrecondition, "{trace:?}: {e:?}");
                }
            }
            Call::LoadSilent => {
                let mut loader = client.clone();
                background.push(tokio::spawn(async move {
                    loader.load_policy(from_learner()).await
                }));
            }
            Call::SetOverlay => {
                let result = client
                    .set_overlay(pb::SetOverlayRequest::default())
                    .await
                    .map(|_| ());
                if latched {
                    refused_while_latched(result);
                } else if let Err(e) = result {
                    assert_eq!(e.code(), Code::FailedPrecondition, "{trace:?}: {e:?}");
                }
            }
        }
        let now = agent_status(&mut client).await;
        if latched {
            assert_eq!(
                agent_state(&now),
                pb::AgentState::EmergencyStopped,
                "{trace:?}"
            );
        }
        tokio::time::sleep(Duration::from_millis(rng.integer_inclusive(0, 150).into())).await;
    }
    // Every load ends within its bound, and the agent can always be
    // stopped, reset and used again.
    for load in background {
        let ended = tokio::time::timeout(Duration::from_secs(10), load).await;
        assert!(ended.is_ok(), "{trace:?}: a load never ended");
    }
    client.emergency_stop(estop()).await.unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    while client
        .reset_emergency_stop(pb::ResetEmergencyStopRequest {})
        .await
        .is_err()
    {
        assert!(Instant::now() < deadline, "{trace:?}: never reset");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(
        agent_state(&agent_status(&mut client).await),
        pb::AgentState::Idle
    );
    client.start_episode(seeded(99)).await.unwrap();
}
