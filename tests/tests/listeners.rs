//! Every listener's front door, tried as an attacker without credentials
//! and as an operator would: more silent TCP connections than the agent
//! may open files (1,100 against a limit of 1,024) neither lock an operator
//! out of EmergencyStop nor make the accept loop spin; a
//! connection that never finishes its handshake is closed in time, on the
//! gRPC and the metrics listener alike; and SIGHUP adds and revokes tokens
//! without a restart.

use std::io::Read;
use std::net::TcpStream;
use std::path::Path;
use std::process::Child;
use std::time::{Duration, Instant};
use tonic::Code;
use tweezer_proto::pb;
use tweezer_proto::pb::hardware_agent_client::HardwareAgentClient;
use tweezer_system_tests::{
    Running, credentials, free_port, run, signal, start_service_with_open_files, stdout_of, write,
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

#[test]
fn more_silent_connections_than_open_files_neither_block_an_emergency_stop_nor_spin_the_agent() {
    tweezer_rpc::raise_open_files_limit(4096);
    let dir = tempfile::tempdir().unwrap();
    let security = server_security(dir.path(), &credentials().dir.join("tokens"));
    let metrics = format!("127.0.0.1:{}", free_port());
    let (agent, addr) = start_agent(&security, &metrics);
    let runtime = tokio::runtime::Runtime::new().unwrap();

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
