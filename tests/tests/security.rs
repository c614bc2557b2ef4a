//! Every service's authentication and authorisation, against real
//! processes over TLS: each RPC called with no token, an unknown token, and
//! a token of each role; health open to all; mutual TLS; plaintext only as
//! the security file says; tokens never in the logs; the CLI's errors.

use std::path::Path;
use std::time::Duration;
use tonic::Code;
use tweezer_proto::pb;
use tweezer_proto::pb::hardware_agent_client::HardwareAgentClient;
use tweezer_proto::pb::learner_client::LearnerClient;
use tweezer_rpc::access::{Access, RULES, access};
use tweezer_rpc::{AuthChannel, ClientSecurity, Role, Security};
use tweezer_system_tests::{
    Running, TINY_ENV, connect, credentials, learner_status, run, start_agent, stderr_of_failure,
    stdout_of, write,
};

/// Who calls: no token, a token no service lists, or one of each role.
const CALLERS: [(&str, Option<Role>); 5] = [
    ("none", None),
    ("stranger", None),
    ("read", Some(Role::Read)),
    ("actor", Some(Role::Actor)),
    ("control", Some(Role::Control)),
];

/// A channel as `caller` (a security file of the test deployment, or
/// `none`: the CA only, no token).
async fn channel(addr: &str, caller: &str) -> AuthChannel {
    if caller != "none" {
        return connect(addr, caller).await;
    }
    let probe = Security::load(Some(Path::new(&credentials().file("probe")))).unwrap();
    ClientSecurity::anonymous(&probe)
        .unwrap()
        .connect(addr, Duration::from_secs(10))
        .await
        .unwrap()
}

/// Calls `method` with a request that changes as little as it can; the
/// status, or OK.
async fn call(channel: AuthChannel, method: &str) -> Result<(), tonic::Status> {
    let mut learner = LearnerClient::new(channel.clone());
    let mut agent = HardwareAgentClient::new(channel.clone());
    let name = method.rsplit('/').next().unwrap();
    match method.split('/').nth(1).unwrap() {
        "tweezer.v1.Learner" => match name {
            "StreamSteps" => learner
                .stream_steps(tokio_stream::iter(Vec::<pb::StepBatch>::new()))
                .await
                .map(drop),
            "GetSnapshot" => learner
                .get_snapshot(pb::SnapshotRequest {
                    selector: Some(pb::snapshot_request::Selector::Version(1)),
                })
                .await
                .map(drop),
            "GetStatus" => learner
                .get_status(pb::LearnerStatusRequest {})
                .await
                .map(drop),
            "ListSnapshots" => learner
                .list_snapshots(pb::ListSnapshotsRequest {})
                .await
                .map(drop),
            "PauseLearning" => learner
                .pause_learning(pb::PauseLearningRequest {})
                .await
                .map(drop),
            "ResumeLearning" => learner
                .resume_learning(pb::ResumeLearningRequest {})
                .await
                .map(drop),
            "Checkpoint" => learner.checkpoint(pb::CheckpointRequest {}).await.map(drop),
            other => panic!("the matrix does not call Learner/{other}: add it"),
        },
        "tweezer.v1.HardwareAgent" => match name {
            "GetStatus" => agent.get_status(pb::AgentStatusRequest {}).await.map(drop),
            "StreamTelemetry" => agent
                .stream_telemetry(pb::TelemetryRequest {})
                .await
                .map(drop),
            "StartEpisode" => agent
                .start_episode(pb::StartEpisodeRequest {
                    target: Some(pb::start_episode_request::Target::RelativeUm(pb::Vector2 {
                        x: f64::NAN,
                        y: 0.0,
                    })),
                    twin_seed: None,
                })
                .await
                .map(drop),
            "StopEpisode" => agent
                .stop_episode(pb::StopEpisodeRequest {})
                .await
                .map(drop),
            "EmergencyStop" => agent
                .emergency_stop(pb::EmergencyStopRequest {
                    reason: "auth matrix".into(),
                })
                .await
                .map(drop),
            "ResetEmergencyStop" => agent
                .reset_emergency_stop(pb::ResetEmergencyStopRequest {})
                .await
                .map(drop),
            "LoadPolicy" => agent
                .load_policy(pb::LoadPolicyRequest {
                    source: Some(pb::load_policy_request::Source::File(
                        "/no/such.safetensors".into(),
                    )),
                    follow: false,
                })
                .await
                .map(drop),
            "SetOverlay" => agent
                .set_overlay(pb::SetOverlayRequest::default())
                .await
                .map(drop),
            other => panic!("the matrix does not call HardwareAgent/{other}: add it"),
        },
        "grpc.reflection.v1.ServerReflection" => {
            use tonic_reflection::pb::v1::ServerReflectionRequest;
            use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
            use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
            let request = ServerReflectionRequest {
                host: String::new(),
                message_request: Some(MessageRequest::ListServices(String::new())),
            };
            let mut replies = ServerReflectionClient::new(channel)
                .server_reflection_info(tokio_stream::iter([request]))
                .await?
                .into_inner();
            replies.message().await.map(drop)
        }
        other => panic!("no service {other}"),
    }
}

/// Every RPC of `service` (and reflection) with every caller: refused as
/// the rules say, with the right code, and let through otherwise.
async fn check_matrix(addr: &str, service: &str) -> usize {
    let mut checked = 0;
    let methods = RULES
        .iter()
        .filter(|(path, _)| path.contains(service) || path.contains("ServerReflection"));
    for (method, needed) in methods {
        assert_eq!(access(method), Access::Needs(*needed));
        for (caller, role) in CALLERS {
            let result = call(channel(addr, caller).await, method).await;
            let code = result.as_ref().err().map(tonic::Status::code);
            match role {
                None => assert_eq!(
                    code,
                    Some(Code::Unauthenticated),
                    "{method} as {caller}: {result:?}"
                ),
                Some(role) if role.grants(*needed) => assert!(
                    !matches!(code, Some(Code::Unauthenticated | Code::PermissionDenied)),
                    "{method} as {caller}: {result:?}"
                ),
                Some(_) => {
                    let status = result.unwrap_err();
                    assert_eq!(
                        status.code(),
                        Code::PermissionDenied,
                        "{method} as {caller}"
                    );
                    assert!(
                        status.message().contains(&format!("needs `{needed}`")),
                        "{}",
                        status.message()
                    );
                }
            }
            checked += 1;
        }
    }
    checked
}

/// The health check, with no token.
async fn healthy(channel: AuthChannel, service: &str) -> bool {
    use tonic_health::pb::health_check_response::ServingStatus;
    tonic_health::pb::health_client::HealthClient::new(channel)
        .check(tonic_health::pb::HealthCheckRequest {
            service: service.into(),
        })
        .await
        .map(|r| r.into_inner().status == ServingStatus::Serving as i32)
        .unwrap_or(false)
}

fn learner_config(dir: &Path) -> String {
    write(
        &dir.join("learner.toml"),
        &format!("{TINY_ENV}\n[learner]\nlisten = \"127.0.0.1:0\"\n"),
    )
}

fn start_learner(dir: &Path, security: &str, run: &str) -> (Running, String) {
    let config = learner_config(dir);
    let log = dir.join(format!("{run}.log"));
    let (child, addr) = tweezer_system_tests::start_learner_with(
        &credentials().file(security),
        &config,
        &dir.join(run),
        Some(&log),
    );
    (Running::new(child), addr)
}

fn secrets() -> Vec<String> {
    ["read", "actor", "control", "stranger"]
        .iter()
        .map(|name| {
            std::fs::read_to_string(credentials().dir.join(format!("{name}.token")))
                .unwrap()
                .trim()
                .to_string()
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_learner_rpc_needs_its_role_and_tokens_stay_out_of_the_logs() {
    let dir = tempfile::tempdir().unwrap();
    let (learner, addr) = start_learner(dir.path(), "server", "run");
    let checked = check_matrix(&addr, "tweezer.v1.Learner").await;
    assert_eq!(checked, 8 * CALLERS.len());
    assert!(healthy(channel(&addr, "none").await, "tweezer.v1.Learner").await);
    assert!(healthy(channel(&addr, "none").await, "").await);
    let (status, _) = learner.stop();
    assert!(status.success());
    let log = std::fs::read_to_string(dir.path().join("run.log")).unwrap();
    assert!(log.contains("call refused"), "{log}");
    assert!(
        log.contains("caller=control"),
        "control calls are logged with the token's name"
    );
    for secret in secrets() {
        assert!(!log.contains(&secret), "a token reached the log");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_hardware_agent_rpc_needs_its_role() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("agent.log");
    let records = dir.path().join("records");
    let (agent, addr) = start_agent(&["--records", records.to_str().unwrap()], Some(&log));
    let agent = Running::new(agent);
    let checked = check_matrix(&addr, "tweezer.v1.HardwareAgent").await;
    assert_eq!(checked, 9 * CALLERS.len());
    assert!(healthy(channel(&addr, "none").await, "tweezer.v1.HardwareAgent").await);
    drop(agent);
    let log = std::fs::read_to_string(&log).unwrap();
    for secret in secrets() {
        assert!(!log.contains(&secret), "a token reached the log");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mutual_tls_refuses_clients_without_a_certificate() {
    let dir = tempfile::tempdir().unwrap();
    let (learner, addr) = start_learner(dir.path(), "server-mtls", "run");
    let status = async |name: &str| learner_status(&addr, name).await.map(drop);
    status("control-cert").await.unwrap();
    let err = status("read").await.unwrap_err();
    assert!(
        err.to_lowercase().contains("certificate"),
        "refused for want of a certificate: {err}"
    );

    // The CLI says what to do.
    let security = credentials().file("read");
    let cli = run(
        "tweezer",
        &[
            "--security",
            &security,
            "learner",
            "--learner",
            &addr,
            "status",
        ],
    );
    let err = stderr_of_failure(&cli);
    assert!(err.contains("client certificate"), "{err}");
    assert!(learner.stop().0.success());
}

#[test]
fn plaintext_only_as_the_file_says_and_the_cli_names_what_is_wrong() {
    let dir = tempfile::tempdir().unwrap();
    let (tls_learner, tls_addr) = start_learner(dir.path(), "server", "tls");
    let (plain_learner, plain_addr) = start_learner(dir.path(), "server-plain", "plain");
    let tweezer = |security: &str, addr: &str, command: &str| {
        let security = credentials().file(security);
        run(
            "tweezer",
            &[
                "--json",
                "--security",
                &security,
                "learner",
                "--learner",
                addr,
                command,
            ],
        )
    };

    // Plaintext with a token works where the service says plaintext; the
    // service warns in its log.
    let out = stdout_of(&tweezer("read-plain", &plain_addr, "status"));
    assert!(out.contains("steps_inserted"), "{out}");
    let log = std::fs::read_to_string(dir.path().join("plain.log")).unwrap();
    assert!(log.contains("TLS is off"), "{log}");

    // A TLS client at a plaintext service, and the reverse.
    let err = stderr_of_failure(&tweezer("read", &plain_addr, "status"));
    assert!(err.contains("does not speak TLS"), "{err}");
    let err = stderr_of_failure(&tweezer("read-plain", &tls_addr, "status"));
    assert!(err.contains("plaintext"), "{err}");

    // A scheme that contradicts the file.
    let err = stderr_of_failure(&tweezer("read", &format!("http://{tls_addr}"), "status"));
    assert!(err.contains("write https://"), "{err}");

    // Bad tokens and wrong roles.
    let err = stderr_of_failure(&tweezer("stranger", &tls_addr, "status"));
    assert!(err.contains("unknown token"), "{err}");
    let err = stderr_of_failure(&tweezer("read", &tls_addr, "pause"));
    assert!(
        err.contains("the token `read` has the `read` role") && err.contains("needs `control`"),
        "{err}"
    );
    let out = stdout_of(&tweezer("control", &tls_addr, "pause"));
    assert!(out.contains("\"paused\":true"), "{out}");

    // A probe needs only the CA: health is open to all.
    let probe = credentials().file("probe");
    let healthy = |service: &str| {
        run(
            "tweezer",
            &[
                "--security",
                &probe,
                "health",
                "--address",
                &tls_addr,
                "--service",
                service,
            ],
        )
    };
    assert_eq!(stdout_of(&healthy("tweezer.v1.Learner")).trim(), "SERVING");
    let unknown = healthy("tweezer.v1.Nothing");
    assert!(!unknown.status.success());
    assert_eq!(
        String::from_utf8_lossy(&unknown.stdout).trim(),
        "SERVICE_UNKNOWN"
    );
    let err = stderr_of_failure(&tweezer("probe", &tls_addr, "status"));
    assert!(
        err.contains("token_file"),
        "a probe cannot read the status: {err}"
    );

    // No security file at all.
    let cli = tweezer_system_tests::output_of(
        std::process::Command::new(tweezer_system_tests::binary("tweezer"))
            .args(["learner", "--learner", &tls_addr, "status"])
            .env_remove(tweezer_rpc::SECURITY_ENV),
    );
    let err = stderr_of_failure(&cli);
    assert!(err.contains("no security file"), "{err}");
    assert!(tls_learner.stop().0.success());
    assert!(plain_learner.stop().0.success());
}

#[test]
fn a_service_without_its_tokens_or_certificate_does_not_start() {
    let dir = tempfile::tempdir().unwrap();
    let config = learner_config(dir.path());
    let missing = write(
        &dir.path().join("no-tokens.toml"),
        &format!(
            "cert = {:?}\nkey = {:?}\n",
            credentials().dir.join("server.crt"),
            credentials().dir.join("server.key")
        ),
    );
    // What `learner serve` says when refused with the security file `file`.
    let refusal = |file: &str| {
        let serve = [
            "serve",
            "--security",
            file,
            "--config",
            &config,
            "--run-dir",
            "unused",
        ];
        stderr_of_failure(&run("learner", &serve))
    };
    let err = refusal(&missing);
    assert!(err.contains("`tokens` is not set"), "{err}");
    let garbled = write(&dir.path().join("garbled.crt"), "not a certificate");
    let bad_cert = write(
        &dir.path().join("bad-cert.toml"),
        &format!(
            "cert = {garbled:?}\nkey = {:?}\ntokens = {:?}\n",
            credentials().dir.join("server.key"),
            credentials().dir.join("tokens")
        ),
    );
    let err = refusal(&bad_cert);
    assert!(
        err.contains("`cert`") && err.contains("bad-cert.toml"),
        "{err}"
    );
    assert!(!Path::new("unused").exists());
}

#[test]
fn certificate_names_cannot_leave_the_output_directory() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("pki");
    let ca = credentials().dir.to_str().unwrap().to_string();
    for name in ["../evil", "sub/evil", "/tmp/evil"] {
        let err = stderr_of_failure(&run(
            "tweezer",
            &[
                "cert",
                "issue",
                "--ca",
                &ca,
                "--name",
                name,
                "--host",
                "localhost",
                "--out",
                out.to_str().unwrap(),
            ],
        ));
        assert!(err.contains("certificate name"), "{err}");
    }
    assert!(!dir.path().join("evil.crt").exists() && !dir.path().join("evil.key").exists());
    assert!(!out.exists(), "nothing is written");
}

#[test]
fn a_service_whose_certificate_is_not_from_its_ca_does_not_start() {
    let dir = tempfile::tempdir().unwrap();
    let other = dir.path().to_str().unwrap();
    stdout_of(&run(
        "tweezer",
        &["cert", "ca", "--out", other, "--days", "2"],
    ));
    stdout_of(&run(
        "tweezer",
        &[
            "cert",
            "issue",
            "--ca",
            other,
            "--name",
            "server",
            "--host",
            "127.0.0.1",
            "--out",
            other,
            "--days",
            "2",
        ],
    ));
    let security = write(
        &dir.path().join("server.toml"),
        &format!(
            "cert = \"server.crt\"\nkey = \"server.key\"\nca = {:?}\ntokens = {:?}\n",
            credentials().dir.join("ca.crt"),
            credentials().dir.join("tokens")
        ),
    );
    let config = learner_config(dir.path());
    let err = stderr_of_failure(&run(
        "learner",
        &[
            "serve",
            "--security",
            &security,
            "--config",
            &config,
            "--run-dir",
            "unused",
        ],
    ));
    assert!(
        err.contains("`cert`") && err.contains("does not chain to the CA"),
        "{err}"
    );
}

/// Whether process `pid` holds or catches SIGHUP (`/proc/PID/status`):
/// before it does, nothing the process could do would save it from one.
/// `None` once it has exited (a zombie, or gone).
fn takes_hangups(pid: u32) -> Option<bool> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| {
        status
            .lines()
            .find_map(|line| line.strip_prefix(name).map(str::trim))
    };
    if field("State:").is_none_or(|state| state.starts_with('Z')) {
        return None;
    }
    let mask = |name| field(name).and_then(|hex| u64::from_str_radix(hex, 16).ok());
    Some(
        [mask("SigBlk:"), mask("SigCgt:")]
            .into_iter()
            .flatten()
            .any(|bits| bits & 1 != 0),
    )
}

/// Starts `bin` with `args`, sends it SIGHUP `after` its first
/// instruction that holds or catches one (before it listens), and checks
/// that it still comes up and stops cleanly.
fn survives_an_early_sighup(bin: &str, args: &[&str], after: Duration) {
    let mut command = std::process::Command::new(tweezer_system_tests::binary(bin));
    command.args(args);
    let (child, addr) = tweezer_system_tests::spawn_service_then(bin, command, None, |child| {
        let deadline = std::time::Instant::now() + Duration::from_secs(30);
        loop {
            match takes_hangups(child.id()) {
                Some(true) => break,
                Some(false) => assert!(
                    std::time::Instant::now() < deadline,
                    "{bin} neither held nor caught SIGHUP within 30 s"
                ),
                None => panic!("{bin} exited before it held or caught SIGHUP"),
            }
            std::thread::sleep(Duration::from_micros(200));
        }
        std::thread::sleep(after);
        tweezer_system_tests::signal(child, "HUP");
    });
    let service = Running::new(child);
    assert!(!addr.is_empty());
    let (status, _) = service.stop();
    assert!(
        status.success(),
        "{bin} after a SIGHUP {after:?} into its start: {status}"
    );
}

#[test]
fn a_sighup_during_start_up_is_a_reload_not_an_exit() {
    let dir = tempfile::tempdir().unwrap();
    let config = learner_config(dir.path());
    let server = credentials().file("server");
    for (i, after) in [0, 20, 150].into_iter().enumerate() {
        let run_dir = dir.path().join(format!("run-{i}"));
        survives_an_early_sighup(
            "learner",
            &[
                "serve",
                "--auto-resume",
                "--security",
                &server,
                "--config",
                &config,
                "--run-dir",
                run_dir.to_str().unwrap(),
            ],
            Duration::from_millis(after),
        );
    }
    let agent_config = credentials().dir.join("agent-control.toml");
    survives_an_early_sighup(
        "hardware-agent",
        &tweezer_system_tests::agent_serve_args(agent_config.to_str().unwrap(), &server),
        Duration::from_millis(0),
    );
}

/// The operator's path of docs/operations.md: `cert issue` and `token new`
/// write the security files, which then work as written.
#[test]
fn cert_and_token_commands_write_security_files_that_work() {
    let dir = tempfile::tempdir().unwrap();
    let pki = dir.path().join("pki");
    let p = pki.to_str().unwrap();
    let tweezer = |args: &[&str]| stdout_of(&run("tweezer", args));
    tweezer(&["cert", "ca", "--out", p, "--days", "2"]);
    // A file the operator started keeps its lines and comments.
    let learner_file = pki.join("learner.toml");
    std::fs::write(
        &learner_file,
        "# the learner's\n[listener]\nmax_connections = 64\n",
    )
    .unwrap();
    let learner = learner_file.to_str().unwrap();
    let out = tweezer(&[
        "cert",
        "issue",
        "--ca",
        p,
        "--name",
        "learner",
        "--host",
        "127.0.0.1",
        "--out",
        p,
        "--days",
        "2",
        "--write-security",
        learner,
    ]);
    assert!(out.contains("key = \"learner.key\""), "{out}");
    // Files elsewhere are named by absolute path.
    let elsewhere = dir.path().join("reader.toml");
    tweezer(&[
        "token",
        "new",
        "--role",
        "read",
        "--name",
        "reader",
        "--tokens",
        &format!("{p}/tokens"),
        "--out",
        &format!("{p}/reader.token"),
        "--write-security",
        elsewhere.to_str().unwrap(),
        "--ca",
        p,
        "--accepted-by",
        learner,
    ]);
    let text = std::fs::read_to_string(&learner_file).unwrap();
    for line in [
        "# the learner's",
        "max_connections = 64",
        "ca = \"ca.crt\"",
        "cert = \"learner.crt\"",
        "key = \"learner.key\"",
        "tokens = \"tokens\"",
    ] {
        assert!(text.contains(line), "{line}: {text}");
    }
    let text = std::fs::read_to_string(&elsewhere).unwrap();
    assert!(
        text.contains(&format!("token_file = \"{p}/reader.token\"")),
        "{text}"
    );
    assert!(text.contains(&format!("ca = \"{p}/ca.crt\"")), "{text}");

    let config = learner_config(dir.path());
    let (child, addr) =
        tweezer_system_tests::start_learner_with(learner, &config, &dir.path().join("run"), None);
    let service = Running::new(child);
    let status = stdout_of(&run(
        "tweezer",
        &[
            "--json",
            "--security",
            elsewhere.to_str().unwrap(),
            "learner",
            "--learner",
            &addr,
            "status",
        ],
    ));
    assert!(status.contains("steps_inserted"), "{status}");
    assert!(service.stop().0.success());

    // A file that would no longer be a security file is left as it was.
    let broken = pki.join("broken.toml");
    std::fs::write(&broken, "plaintext = \"yes\"\n").unwrap();
    let err = stderr_of_failure(&run(
        "tweezer",
        &[
            "token",
            "new",
            "--role",
            "read",
            "--name",
            "other",
            "--tokens",
            &format!("{p}/tokens"),
            "--out",
            &format!("{p}/other.token"),
            "--write-security",
            broken.to_str().unwrap(),
        ],
    ));
    assert!(err.contains("not a security file"), "{err}");
    assert_eq!(
        std::fs::read_to_string(&broken).unwrap(),
        "plaintext = \"yes\"\n"
    );
}
