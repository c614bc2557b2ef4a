//! Every listener's front door, tried as an attacker without credentials
//! and as an operator would: more silent TCP connections than the agent
//! may open files (1,100 against a limit of 1,024) neither lock an operator
//! out of EmergencyStop nor make the accept loop spin; a
//! connection that never finishes its handshake is closed in time, on the
//! gRPC and the metrics listener alike; and SIGHUP adds and revokes tokens
//! without a restart.

use std::collections::VecDeque;
use std::io::Read;
use std::net::TcpStream;
use std::path::Path;
use std::process::Child;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tonic::Code;
use tweezer_proto::pb;
use tweezer_proto::pb::hardware_agent_client::HardwareAgentClient;
use tweezer_proto::pb::learner_client::LearnerClient;
use tweezer_rpc::Security;
use tweezer_system_tests::{
    Running, TINY_ENV, credentials, free_port, run, signal, start_learner_with,
    start_service_with_open_files, stdout_of, write,
};

/// A security file serving the test deployment's certificate with the
/// tokens file `tokens`, and connection limits for quick tests.
fn server_security(dir: &Path, tokens: &Path) -> String {
    let creds = credentials().dir.display().to_string();
    write(
        &dir.join("server.toml"),
        &format!(
            "cert = \"{creds}/server.crt\"\nkey = \"{creds}/server.key\"\nca = \"{creds}/ca.crt\"\n\
             tokens = \"{}\"\n\n[listener]\nhandshake_timeout_s = 1.0\nidle_timeout_s = 60.0\n\
             max_handshakes = 32\n",
            tokens.display()
        ),
    )
}

/// The agent on the twin with `security`, its metrics on `metrics`, and at
/// most 1,024 open files (a common default).
fn start_agent(security: &str, metrics: &str) -> (Running, String) {
    let config = credentials().dir.join("agent-control.toml");
    let (child, addr) = start_service_with_open_files(
        "hardware-agent",
        &[
            "--config",
            config.to_str().unwrap(),
            "serve",
            "--twin",
            "--greedy",
            "--listen",
            "127.0.0.1:0",
            "--metrics-listen",
            metrics,
            "--security",
            security,
        ],
        1024,
    );
    (Running::new(child), addr)
}

/// CPU seconds (user + system) the process `pid` has used.
fn cpu_seconds(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    // Fields after the command's closing parenthesis; utime and stime are
    // the 14th and 15th of the line, in clock ticks (100 per second).
    let rest = &stat[stat.rfind(')').unwrap() + 2..];
    let fields: Vec<&str> = rest.split(' ').collect();
    let ticks: f64 = fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap();
    ticks / 100.0
}

/// Waits until `stream` is closed by the server; how long that took.
fn closed_within(mut stream: TcpStream, limit: Duration) -> Duration {
    let start = Instant::now();
    stream.set_read_timeout(Some(limit)).unwrap();
    let mut byte = [0u8; 1];
    match stream.read(&mut byte) {
        Ok(0) => start.elapsed(),
        Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => start.elapsed(),
        other => panic!("the silent connection is still open after {limit:?}: {other:?}"),
    }
}

async fn emergency_stop(addr: &str) -> Result<pb::AgentStatus, tonic::Status> {
    let channel = credentials()
        .client("control")
        .connect(addr, Duration::from_secs(5))
        .await
        .map_err(|e| tonic::Status::unavailable(e.to_string()))?;
    let mut client = HardwareAgentClient::new(channel);
    let request = pb::EmergencyStopRequest {
        reason: "listener test".into(),
    };
    tokio::time::timeout(Duration::from_secs(5), client.emergency_stop(request))
        .await
        .map_err(|_| tonic::Status::deadline_exceeded("no reply within 5 s"))?
        .map(tonic::Response::into_inner)
}

/// An agent with the test deployment's tokens and quick limits, and a
/// runtime for calls to it; the directory of its security file, and its
/// metrics address.
fn quick_agent() -> (
    tempfile::TempDir,
    Running,
    String,
    String,
    tokio::runtime::Runtime,
) {
    tweezer_rpc::raise_open_files_limit(4096);
    let dir = tempfile::tempdir().unwrap();
    let security = server_security(dir.path(), &credentials().dir.join("tokens"));
    let metrics = format!("127.0.0.1:{}", free_port());
    let (agent, addr) = start_agent(&security, &metrics);
    (
        dir,
        agent,
        addr,
        metrics,
        tokio::runtime::Runtime::new().unwrap(),
    )
}

#[test]
fn more_silent_connections_than_open_files_neither_block_an_emergency_stop_nor_spin_the_agent() {
    let (_dir, agent, addr, metrics, runtime) = quick_agent();

    let before = emergency_stop(&addr);
    runtime
        .block_on(before)
        .expect("an e-stop on a quiet agent");
    // More than the agent may open: each would hold a descriptor for good.
    let silent: Vec<TcpStream> = (0..1100)
        .map(|i| {
            let target = if i % 10 == 0 { &metrics } else { &addr };
            TcpStream::connect(target).expect("a TCP connection")
        })
        .collect();
    std::thread::sleep(Duration::from_millis(300));

    let cpu = cpu_seconds(agent.child().id());
    let started = Instant::now();
    let status = runtime
        .block_on(emergency_stop(&addr))
        .expect("EmergencyStop answers beside 1,100 silent connections");
    let reply = started.elapsed();
    assert_eq!(status.state, pb::AgentState::EmergencyStopped as i32);
    eprintln!("EmergencyStop (connect, TLS, call) beside 1,100 silent connections: {reply:?}");
    assert!(reply < Duration::from_secs(3), "took {reply:?}");

    std::thread::sleep(Duration::from_secs(2));
    let used = cpu_seconds(agent.child().id()) - cpu;
    let window = started.elapsed().as_secs_f64();
    eprintln!("agent CPU while they stay connected: {used:.2} s in {window:.1} s");
    assert!(
        used < 0.5 * window,
        "the agent used {used:.2} CPU s in {window:.1} s: the accept loop spins"
    );
    drop(silent);
    let (status, _) = agent.stop();
    assert!(status.success(), "the agent exits cleanly: {status}");
}

#[test]
fn connections_that_never_finish_a_handshake_are_closed_on_every_listener() {
    let dir = tempfile::tempdir().unwrap();
    let security = server_security(dir.path(), &credentials().dir.join("tokens"));
    let metrics = format!("127.0.0.1:{}", free_port());
    let (agent, addr) = start_agent(&security, &metrics);
    for target in [&addr, &metrics] {
        let stream = TcpStream::connect(target).unwrap();
        let took = closed_within(stream, Duration::from_secs(5));
        assert!(
            took >= Duration::from_millis(800),
            "{target}: closed after {took:?}"
        );
    }
    // Half a TLS ClientHello, then silence.
    let mut stream = TcpStream::connect(&addr).unwrap();
    std::io::Write::write_all(&mut stream, &[0x16, 0x03, 0x01, 0x02, 0x00, 0x01]).unwrap();
    closed_within(stream, Duration::from_secs(5));
    let (status, _) = agent.stop();
    assert!(status.success());
}

fn new_token(tokens: &Path, name: &str, out: &Path) {
    stdout_of(&run(
        "tweezer",
        &[
            "token",
            "new",
            "--role",
            "control",
            "--name",
            name,
            "--tokens",
            tokens.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
    ));
}

async fn status_with(addr: &str, token_file: &Path) -> Result<pb::AgentStatus, Code> {
    let creds = credentials().dir.display().to_string();
    let dir = token_file.parent().unwrap();
    let file = write(
        &dir.join(format!(
            "{}.toml",
            token_file.file_stem().unwrap().to_str().unwrap()
        )),
        &format!(
            "ca = \"{creds}/ca.crt\"\ntoken_file = \"{}\"\n",
            token_file.display()
        ),
    );
    let security = tweezer_rpc::Security::load(Some(Path::new(&file))).unwrap();
    let channel = tweezer_rpc::ClientSecurity::load(&security)
        .unwrap()
        .connect(addr, Duration::from_secs(5))
        .await
        .unwrap();
    HardwareAgentClient::new(channel)
        .get_status(pb::AgentStatusRequest {})
        .await
        .map(tonic::Response::into_inner)
        .map_err(|status| status.code())
}

#[test]
fn sighup_adds_and_revokes_tokens_without_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = dir.path().join("tokens");
    let first = dir.path().join("first.token");
    new_token(&tokens, "first", &first);
    let security = server_security(dir.path(), &tokens);
    let metrics = format!("127.0.0.1:{}", free_port());
    let (agent, addr) = start_agent(&security, &metrics);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let hup = |child: &Child| {
        signal(child, "HUP");
        std::thread::sleep(Duration::from_millis(500));
    };

    let second = dir.path().join("second.token");
    new_token(&tokens, "second", &second);
    assert_eq!(
        runtime.block_on(status_with(&addr, &second)).unwrap_err(),
        Code::Unauthenticated,
        "read once at start"
    );
    hup(agent.child());
    runtime
        .block_on(status_with(&addr, &second))
        .expect("the token added before SIGHUP is accepted");

    // Revoke `first`; a broken tokens file is refused and the old kept.
    let text = std::fs::read_to_string(&tokens).unwrap();
    write(&tokens, "this is not a tokens file\n");
    hup(agent.child());
    runtime
        .block_on(status_with(&addr, &first))
        .expect("a broken tokens file keeps the previous tokens");
    let kept: String = text
        .lines()
        .filter(|line| !line.contains(" first "))
        .map(|line| format!("{line}\n"))
        .collect();
    write(&tokens, &kept);
    hup(agent.child());
    assert_eq!(
        runtime.block_on(status_with(&addr, &first)).unwrap_err(),
        Code::Unauthenticated,
        "revoked"
    );
    runtime.block_on(status_with(&addr, &second)).unwrap();
    let (status, _) = agent.stop();
    assert!(status.success(), "SIGHUP does not end the agent: {status}");
}

/// Percentile `p` (0..=1) of `sorted`.
fn percentile(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

#[test]
fn an_emergency_stop_gets_through_a_peers_storm_of_silent_connects() {
    let (_dir, agent, addr, _metrics, runtime) = quick_agent();
    runtime
        .block_on(emergency_stop(&addr))
        .expect("an e-stop on a quiet agent");

    // A peer (127.0.0.2; the operator is 127.0.0.1) whose two threads hold
    // 300 silent connections each and open a new one the moment they can,
    // dropping their oldest: a stream of connects that never send a byte,
    // as fast as this machine makes them.
    let storming = Arc::new(AtomicBool::new(true));
    let connects = Arc::new(AtomicU64::new(0));
    let target: std::net::SocketAddr = addr.parse().unwrap();
    let storm: Vec<_> = (0..2)
        .map(|_| {
            let (storming, connects) = (storming.clone(), connects.clone());
            std::thread::spawn(move || {
                let mut held = VecDeque::new();
                let peer = std::net::SocketAddr::from(([127, 0, 0, 2], 0));
                let connect = || -> std::io::Result<socket2::Socket> {
                    let socket =
                        socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None)?;
                    socket.bind(&peer.into())?;
                    socket.connect_timeout(&target.into(), Duration::from_millis(100))?;
                    Ok(socket)
                };
                while storming.load(Ordering::Relaxed) {
                    let Ok(stream) = connect() else {
                        continue;
                    };
                    connects.fetch_add(1, Ordering::Relaxed);
                    held.push_back(stream);
                    if held.len() > 300 {
                        held.pop_front();
                    }
                }
            })
        })
        .collect();
    std::thread::sleep(Duration::from_millis(500));

    // 20 e-stops, 100 ms apart, each on a new connection.
    let started = Instant::now();
    let before = connects.load(Ordering::Relaxed);
    let mut answered = Vec::new();
    let mut failures = Vec::new();
    for _ in 0..20 {
        let call = Instant::now();
        match runtime.block_on(emergency_stop(&addr)) {
            Ok(status) => {
                assert_eq!(status.state, pb::AgentState::EmergencyStopped as i32);
                answered.push(call.elapsed());
            }
            Err(status) => failures.push(status.to_string()),
        }
        std::thread::sleep(Duration::from_millis(100).saturating_sub(call.elapsed()));
    }
    let rate = (connects.load(Ordering::Relaxed) - before) as f64 / started.elapsed().as_secs_f64();
    storming.store(false, Ordering::Relaxed);
    for thread in storm {
        thread.join().unwrap();
    }
    answered.sort();
    eprintln!(
        "EmergencyStop under {rate:.0} silent connects/s from another address: {} of 20 answered, median {:?}, p99 {:?}",
        answered.len(),
        answered.get(answered.len() / 2),
        answered.last().map(|_| percentile(&answered, 0.99)),
    );
    assert!(
        failures.is_empty(),
        "{} of 20 e-stops failed under the storm: {failures:?}",
        failures.len()
    );
    let (status, _) = agent.stop();
    assert!(status.success(), "the agent exits cleanly: {status}");
}

/// A plaintext security file with `tokens`, for tests that write bytes to
/// the listener themselves.
fn plain_server_security(dir: &Path, listener: &str) -> String {
    let tokens = credentials().dir.join("tokens");
    write(
        &dir.join("plain-server.toml"),
        &format!("plaintext = true\ntokens = {tokens:?}\n\n[listener]\n{listener}",),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_quiet_authenticated_stream_outlasts_any_number_of_silent_strangers() {
    let dir = tempfile::tempdir().unwrap();
    let security = plain_server_security(
        dir.path(),
        "max_connections = 8\nhandshake_timeout_s = 5.0\nidle_timeout_s = 60.0\n",
    );
    let config = write(
        &dir.path().join("learner.toml"),
        &format!("{TINY_ENV}\n[learner]\nlisten = \"127.0.0.1:0\"\n"),
    );
    let (learner, addr) = start_learner_with(&security, &config, &dir.path().join("run"), None);
    let learner = Running::new(learner);
    let actor = write(
        &dir.path().join("actor-plain.toml"),
        &format!(
            "plaintext = true\ntoken_file = {:?}\n",
            credentials().dir.join("actor.token")
        ),
    );
    let channel =
        tweezer_rpc::ClientSecurity::load(&Security::load(Some(Path::new(&actor))).unwrap())
            .unwrap()
            .connect(&addr, Duration::from_secs(10))
            .await
            .unwrap();
    // An actor's stream, opened and then quiet: nothing to send yet.
    let (_batches, outbound) = tokio::sync::mpsc::channel::<pb::StepBatch>(1);
    let mut acks = LearnerClient::new(channel)
        .stream_steps(tokio_stream::wrappers::ReceiverStream::new(outbound))
        .await
        .expect("the stream opens")
        .into_inner();

    // Strangers, each of whom says one byte and then nothing, four times
    // as many as the cap, each newer and more recently heard from.
    let mut strangers = Vec::new();
    for _ in 0..32 {
        let mut stranger = tokio::net::TcpStream::connect(&addr).await.unwrap();
        tokio::io::AsyncWriteExt::write_all(&mut stranger, b"P")
            .await
            .unwrap();
        strangers.push(stranger);
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let waited = tokio::time::timeout(Duration::from_secs(1), acks.message()).await;
    assert!(
        waited.is_err(),
        "the quiet actor's stream was closed among silent strangers: {waited:?}"
    );
    drop(strangers);
    assert!(learner.stop().0.success());
}

#[test]
fn a_token_revoked_by_sighup_stops_the_streams_it_opened() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = dir.path().join("tokens");
    std::fs::copy(credentials().dir.join("tokens"), &tokens).unwrap();
    let security = server_security(dir.path(), &tokens);
    let addr = format!("127.0.0.1:{}", free_port());
    let learner_config = write(
        &dir.path().join("learner.toml"),
        &format!(
            "{TINY_ENV}\n[learner]\nlisten = \"{addr}\"\nuniform_steps = 300\n\
             [learner.limiter]\nmin_size = 200\nupdates_per_insert = 0.25\n"
        ),
    );
    let log = dir.path().join("learner.log");
    let (learner, _) = start_learner_with(
        &security,
        &learner_config,
        &dir.path().join("run"),
        Some(&log),
    );
    let learner = Running::new(learner);
    let actor_config = write(
        &dir.path().join("actor.toml"),
        &format!("{TINY_ENV}\n[actor]\nlearner = \"{addr}\"\nenvs = 4\nbatch_steps = 50\n"),
    );
    let actor = Running::new(
        std::process::Command::new(tweezer_system_tests::binary("actor"))
            .args(["--config", &actor_config, "run"])
            .args(["--security", &credentials().file("actor")])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap(),
    );
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let steps = || tweezer_system_tests::status(&runtime, &addr).map_or(0, |s| s.steps_inserted);
    tweezer_system_tests::wait_for_learner(
        &runtime,
        &addr,
        "storing the actor's steps",
        Duration::from_secs(120),
        |s| s.steps_inserted >= 500,
    );

    // Revoke the actor's token: its open stream is cut.
    let text = std::fs::read_to_string(&tokens).unwrap();
    let kept: String = text
        .lines()
        .filter(|line| !line.contains(" actor "))
        .map(|line| format!("{line}\n"))
        .collect();
    write(&tokens, &kept);
    signal(learner.child(), "HUP");
    std::thread::sleep(Duration::from_secs(1));
    let after = steps();
    std::thread::sleep(Duration::from_secs(3));
    assert_eq!(
        steps(),
        after,
        "steps arrive on a stream whose token was revoked"
    );
    drop(actor);
    let (status, _) = learner.stop();
    assert!(status.success());
    let log = std::fs::read_to_string(&log).unwrap();
    assert!(log.contains("token was revoked"), "{log}");
}

#[test]
fn a_certificate_from_another_ca_is_refused_on_sighup() {
    let dir = tempfile::tempdir().unwrap();
    let creds = credentials().dir.clone();
    for file in ["server.crt", "server.key"] {
        std::fs::copy(creds.join(file), dir.path().join(file)).unwrap();
    }
    let security = write(
        &dir.path().join("server.toml"),
        &format!(
            "cert = \"server.crt\"\nkey = \"server.key\"\nca = {:?}\ntokens = {:?}\n",
            creds.join("ca.crt"),
            creds.join("tokens")
        ),
    );
    let metrics = format!("127.0.0.1:{}", free_port());
    let (agent, addr) = start_agent(&security, &metrics);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let control = creds.join("control.token");
    runtime.block_on(status_with(&addr, &control)).unwrap();

    // Another CA's certificate for the same names, and its key.
    let other = dir.path().join("other");
    let other_dir = other.to_str().unwrap();
    stdout_of(&run(
        "tweezer",
        &["cert", "ca", "--out", other_dir, "--days", "2"],
    ));
    stdout_of(&run(
        "tweezer",
        &[
            "cert",
            "issue",
            "--ca",
            other_dir,
            "--name",
            "server",
            "--host",
            "127.0.0.1",
            "--host",
            "localhost",
            "--out",
            other_dir,
            "--days",
            "2",
        ],
    ));
    for file in ["server.crt", "server.key"] {
        std::fs::copy(other.join(file), dir.path().join(file)).unwrap();
    }
    signal(agent.child(), "HUP");
    std::thread::sleep(Duration::from_millis(500));
    runtime
        .block_on(status_with(&addr, &control))
        .expect("clients that trust the deployment's CA are still served");
    let (status, _) = agent.stop();
    assert!(status.success());
}
