//! The `hardware-agent serve` daemon on the digital twin, over gRPC on a
//! real socket: status, overlay, episodes, telemetry, emergency stop and
//! its reset, refusals, and shutdown on SIGTERM.

use std::time::{Duration, Instant};
use tonic::Code;
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tweezer_proto::pb;
use tweezer_proto::pb::hardware_agent_client::HardwareAgentClient;
use tweezer_rpc::AuthChannel;
use tweezer_system_tests::{
    Running, agent_state, agent_status, connect, start_agent, wait_for_agent_state,
};

/// The daemon, killed if the test fails before stopping it, and its address.
fn start(records: &std::path::Path) -> (Running, String) {
    let (child, addr) = start_agent(
        &["--rate", "20", "--records", records.to_str().unwrap()],
        None,
    );
    (Running::new(child), addr)
}

/// The services gRPC reflection lists.
async fn list_services(channel: AuthChannel) -> Vec<String> {
    use tonic_reflection::pb::v1::ServerReflectionRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    let request = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut replies = ServerReflectionClient::new(channel)
        .server_reflection_info(tokio_stream::iter([request]))
        .await
        .unwrap()
        .into_inner();
    let reply = replies.message().await.unwrap().unwrap();
    match reply.message_response {
        Some(MessageResponse::ListServicesResponse(list)) => {
            list.service.into_iter().map(|s| s.name).collect()
        }
        other => panic!("unexpected reflection reply {other:?}"),
    }
}

fn seeded(seed: u64) -> pb::StartEpisodeRequest {
    pb::StartEpisodeRequest {
        target: None,
        twin_seed: Some(seed),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_daemon_runs_episodes_stops_them_and_refuses_what_it_must() {
    let dir = tempfile::tempdir().unwrap();
    let (daemon, addr) = start(dir.path());
    let mut client = HardwareAgentClient::new(connect(&addr, "control").await);

    let status =
        wait_for_agent_state(&mut client, pb::AgentState::Idle, Duration::from_secs(5)).await;
    assert_eq!(status.policy, "greedy baseline");

    // The standard services: health and reflection.
    let channel = connect(&addr, "read").await;
    let health = HealthClient::new(channel.clone())
        .check(HealthCheckRequest {
            service: "tweezer.v1.HardwareAgent".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(health.status, ServingStatus::Serving as i32);
    let services = list_services(channel).await;
    assert!(
        services.contains(&"tweezer.v1.HardwareAgent".to_string()),
        "{services:?}"
    );

    // Bad requests are named and change nothing.
    let far = pb::StartEpisodeRequest {
        target: Some(pb::start_episode_request::Target::RelativeUm(pb::Vector2 {
            x: 20_000.0,
            y: 0.0,
        })),
        twin_seed: None,
    };
    let err = client.start_episode(far).await.unwrap_err();
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(err.message().contains("travel limits"), "{}", err.message());
    let err = client
        .load_policy(pb::LoadPolicyRequest {
            source: Some(pb::load_policy_request::Source::File(
                "/no/such.safetensors".into(),
            )),
            follow: false,
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(
        err.message().contains("/no/such.safetensors"),
        "{}",
        err.message()
    );
    let bad_wall = pb::SetOverlayRequest {
        discs_um: vec![],
        walls: vec![pb::Wall {
            from_um: Some(pb::Vector2 {
                x: 0.0,
                y: f64::NAN,
            }),
            to_um: None,
        }],
    };
    let err = client.set_overlay(bad_wall).await.unwrap_err();
    assert!(
        err.message().contains("walls[0].from_um"),
        "{}",
        err.message()
    );

    // A virtual wall 20 µm below the trap: seed 1's target lies ~91 µm
    // below, so the greedy policy drives into the wall and collides.
    let wall = pb::SetOverlayRequest {
        discs_um: vec![],
        walls: vec![pb::Wall {
            from_um: Some(pb::Vector2 { x: -60.0, y: 20.0 }),
            to_um: Some(pb::Vector2 { x: 60.0, y: 20.0 }),
        }],
    };
    let status = client.set_overlay(wall).await.unwrap().into_inner();
    assert!(status.virtual_obstacles > 40);
    let mut telemetry = client
        .stream_telemetry(pb::TelemetryRequest {})
        .await
        .unwrap()
        .into_inner();
    let status = client.start_episode(seeded(1)).await.unwrap().into_inner();
    assert_eq!(agent_state(&status), pb::AgentState::Running);
    let err = client.start_episode(seeded(1)).await.unwrap_err();
    assert_eq!(
        err.code(),
        Code::FailedPrecondition,
        "one episode at a time"
    );
    let mut saw_virtual = false;
    let outcome = loop {
        let message = telemetry.message().await.unwrap().unwrap();
        let outcome = pb::Outcome::try_from(message.outcome).unwrap();
        if outcome != pb::Outcome::Running {
            break outcome;
        }
        let centres = message.observation.unwrap().centres;
        saw_virtual |= centres
            .chunks(2)
            .any(|c| (c[1] - (512.0 + 216.0)).abs() < 30.0);
    };
    assert_eq!(outcome, pb::Outcome::Collision);
    assert!(saw_virtual, "the wall was in the observations");
    // Once the feed says the episode ended, the status says so too.
    let status = agent_status(&mut client).await;
    assert_eq!(agent_state(&status), pb::AgentState::Idle);
    assert_eq!(status.last_outcome, pb::Outcome::Collision as i32);

    // Without the wall, an emergency stop in mid-episode: the reply comes
    // at once, motion stops, and nothing moves until the stop is reset.
    client
        .set_overlay(pb::SetOverlayRequest::default())
        .await
        .unwrap();
    client.start_episode(seeded(2)).await.unwrap();
    tokio::time::sleep(Duration::from_millis(600)).await;
    let asked = Instant::now();
    let status = client
        .emergency_stop(pb::EmergencyStopRequest {
            reason: "test".into(),
        })
        .await
        .unwrap()
        .into_inner();
    // The reply does not wait for the episode, which would run on for
    // seconds; a second of slack leaves a loaded 2-core machine room.
    let latency = asked.elapsed();
    assert!(latency < Duration::from_secs(1), "{latency:?}");
    assert_eq!(agent_state(&status), pb::AgentState::EmergencyStopped);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let stopped = agent_status(&mut client).await;
    assert_eq!(agent_state(&stopped), pb::AgentState::EmergencyStopped);
    assert_eq!(stopped.last_outcome, pb::Outcome::Stopped as i32);
    assert_eq!(stopped.message, "test");
    let err = client.start_episode(seeded(3)).await.unwrap_err();
    assert_eq!(err.code(), Code::FailedPrecondition);
    assert!(
        err.message().contains("emergency stop"),
        "{}",
        err.message()
    );
    let status = client
        .reset_emergency_stop(pb::ResetEmergencyStopRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(agent_state(&status), pb::AgentState::Idle);

    // SIGTERM ends the daemon cleanly, within 10 s.
    let asked = Instant::now();
    let (exit, _) = daemon.stop();
    assert!(asked.elapsed() < Duration::from_secs(10), "slow to stop");
    assert!(exit.success(), "{exit:?}");
    let records = std::fs::read_dir(dir.path()).unwrap().count();
    assert_eq!(records, 4, "two episodes: a record and a picture each");
}

/// A SIGTERM the moment the daemon says it listens (a supervisor that
/// changes its mind) is caught, not left to end it at once with its stages
/// unstopped.
#[test]
fn a_sigterm_as_soon_as_the_daemon_listens_ends_it_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    for _ in 0..3 {
        let (child, _) = start_agent(&["--records", dir.path().to_str().unwrap()], None);
        let (exit, _) = Running::new(child).stop();
        assert!(exit.success(), "{exit:?}");
    }
}
