//! Helpers for the system tests, which start the workspace's binaries as
//! real processes.

use serde_json::Value;
use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Output, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};
use tweezer_proto::pb;
use tweezer_proto::pb::hardware_agent_client::HardwareAgentClient;
use tweezer_proto::pb::learner_client::LearnerClient;

/// An `[env]` table without free spheres and with 20 x 16 images: cheap to
/// step and to learn from.
pub const TINY_ENV: &str = r#"
[env]
min_free_spheres = 0
max_free_spheres = 0
time_limit = 200
[env.image]
width = 20
height = 16
"#;

/// The `[control]` table of every hardware agent the system tests start: a
/// step may start up to five seconds late. The tests drive the twin on a
/// shared, loaded machine that cannot promise the instrument's 100 ms, and
/// no test may depend on the scheduler meeting a deadline; the deadline
/// itself is tested on its own, with an injected stall
/// (`hardware-agent/tests/loop_interruptions.rs`).
pub const AGENT_CONTROL: &str = "[control]\ndeadline_margin_ms = 5000\n";

/// Every binary of the workspace by name, built once per test process by
/// `cargo build --workspace --all-targets`: the same targets, and so the
/// same feature resolution, as `cargo test --workspace`, which makes the
/// build a no-op there instead of a second build of every dependency.
fn binaries() -> &'static HashMap<String, PathBuf> {
    static BINARIES: OnceLock<HashMap<String, PathBuf>> = OnceLock::new();
    BINARIES.get_or_init(|| {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let manifest = Path::new(env!("CARGO_MANIFEST_DIR")).join("../Cargo.toml");
        let output = output_of(
            Command::new(cargo)
                .args([
                    "build",
                    "--workspace",
                    "--all-targets",
                    "--message-format=json",
                ])
                .arg("--manifest-path")
                .arg(manifest),
        );
        assert!(
            output.status.success(),
            "cargo build failed:\n{}",
            String::from_utf8_lossy(&output.stderr)
        );
        String::from_utf8_lossy(&output.stdout)
            .lines()
            .filter_map(|line| serde_json::from_str::<Value>(line).ok())
            .filter(|m| m["reason"] == "compiler-artifact" && m["profile"]["test"] == false)
            .filter(|m| {
                m["target"]["kind"]
                    .as_array()
                    .is_some_and(|k| k.iter().any(|k| k == "bin"))
            })
            .filter_map(|m| {
                let name = m["target"]["name"].as_str()?.to_string();
                let path = PathBuf::from(m["executable"].as_str()?);
                Some((name, path))
            })
            .collect()
    })
}

/// The path of the workspace binary `bin`.
pub fn binary(bin: &str) -> &'static Path {
    binaries()
        .get(bin)
        .unwrap_or_else(|| panic!("the workspace has no binary `{bin}`"))
}

/// The longest a process that a test runs to completion may take: the
/// slowest, a pip install or a sweep of short trainings, takes a few
/// minutes on a loaded 2-core runner.
pub const RUN_LIMIT: Duration = Duration::from_secs(15 * 60);

/// Runs `command` to completion, its output captured. Past [`RUN_LIMIT`]
/// it is killed and the test fails with what it printed, rather than
/// hanging the test run; so does a run whose output a process it started
/// still holds open after it exited.
pub fn output_of(command: &mut Command) -> Output {
    let program = command.get_program().to_string_lossy().into_owned();
    let child = command
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {program}: {e}"));
    output_within(child, RUN_LIMIT, &program)
}

/// `child`'s exit status and the output of its piped streams, waited for
/// up to `limit`. Past it the process (`what`) is killed and the test
/// fails with what it printed; so does a process that exited while one it
/// started still holds its output open at the limit.
pub fn output_within(mut child: Child, limit: Duration, what: &str) -> Output {
    let deadline = Instant::now() + limit;
    let stdout = child.stdout.take().map(Drained::start);
    let stderr = child.stderr.take().map(Drained::start);
    let status = exit_by(&mut child, deadline);
    if status.is_none() {
        let _ = child.kill();
        let _ = child.wait();
    }
    // The pipes close when the last process holding them exits: the child,
    // or one it started and left running. After a kill, a few seconds.
    let ends = deadline.max(Instant::now() + Duration::from_secs(5));
    let closed = [&stdout, &stderr]
        .iter()
        .all(|pipe| pipe.as_ref().is_none_or(|pipe| pipe.closed_by(ends)));
    let text = |pipe: &Option<Drained>| pipe.as_ref().map(Drained::text).unwrap_or_default();
    let printed = || format!("{}{}", text(&stdout), text(&stderr));
    let bytes = |pipe: &Option<Drained>| pipe.as_ref().map(Drained::bytes).unwrap_or_default();
    match status {
        None => panic!("{what} ran past {limit:?} and was killed:\n{}", printed()),
        Some(_) if !closed => panic!(
            "{what} exited, but a process it started still holds its output open:\n{}",
            printed()
        ),
        Some(status) => Output {
            status,
            stdout: bytes(&stdout),
            stderr: bytes(&stderr),
        },
    }
}

/// A pipe read to its end on a thread of its own, what it gave kept as it
/// arrives, so that a run that never closes it still shows its output.
struct Drained {
    bytes: std::sync::Arc<std::sync::Mutex<Vec<u8>>>,
    end: std::sync::mpsc::Receiver<()>,
}

impl Drained {
    fn start(mut pipe: impl std::io::Read + Send + 'static) -> Self {
        let bytes = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let (sender, end) = std::sync::mpsc::channel();
        let kept = bytes.clone();
        std::thread::spawn(move || {
            let mut chunk = [0; 8192];
            while let Ok(n @ 1..) = pipe.read(&mut chunk) {
                kept.lock()
                    .expect("unpoisoned")
                    .extend_from_slice(&chunk[..n]);
            }
            let _ = sender.send(());
        });
        Self { bytes, end }
    }

    /// Whether the pipe closed by `deadline`.
    fn closed_by(&self, deadline: Instant) -> bool {
        let left = deadline.saturating_duration_since(Instant::now());
        self.end.recv_timeout(left).is_ok()
    }

    fn bytes(&self) -> Vec<u8> {
        self.bytes.lock().expect("unpoisoned").clone()
    }

    fn text(&self) -> String {
        String::from_utf8_lossy(&self.bytes()).into_owned()
    }
}

/// `child`'s exit status, waited for until `deadline`; `None` if it still
/// runs then.
fn exit_by(child: &mut Child, deadline: Instant) -> Option<ExitStatus> {
    loop {
        if let Some(status) = child.try_wait().expect("wait works") {
            return Some(status);
        }
        if Instant::now() >= deadline {
            return None;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Runs binary `bin` with `args` to completion (within [`RUN_LIMIT`]).
pub fn run(bin: &str, args: &[&str]) -> Output {
    output_of(Command::new(binary(bin)).args(args))
}

/// Standard output of a run that must succeed.
pub fn stdout_of(output: &Output) -> String {
    assert!(
        output.status.success(),
        "exit {:?}\nstderr: {}",
        output.status,
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout.clone()).expect("utf-8 output")
}

/// Standard error of a run that must fail.
pub fn stderr_of_failure(output: &Output) -> String {
    assert!(!output.status.success(), "expected failure, got success");
    String::from_utf8_lossy(&output.stderr).into_owned()
}

/// The test deployment's credentials, made once per test process with the
/// `tweezer cert` and `tweezer token` commands: a CA, a certificate for
/// loopback (`server`) and one for a client (`client`), a token of each
/// role and a `stranger` token the services do not list, and a security
/// file for each use.
pub struct Credentials {
    /// Where they are.
    pub dir: PathBuf,
}

impl Credentials {
    /// The security file `name`: `server` (certificate, key, tokens, and a
    /// read token for fetching snapshots), `server-mtls` (and requiring
    /// client certificates), `read`, `actor`, `control`, `stranger`
    /// (clients with that token), `control-cert` (and the client
    /// certificate), `server-plain` and `read-plain` (plaintext), `probe`
    /// (the CA only, no token).
    pub fn file(&self, name: &str) -> String {
        let path = self.dir.join(format!("{name}.toml"));
        assert!(path.is_file(), "no security file {}", path.display());
        path.to_str().expect("a UTF-8 path").to_string()
    }

    /// The client settings of the security file `name`.
    pub fn client(&self, name: &str) -> tweezer_rpc::ClientSecurity {
        let security = tweezer_rpc::Security::load(Some(Path::new(&self.file(name))))
            .expect("the security file loads");
        tweezer_rpc::ClientSecurity::load(&security).expect("the client settings load")
    }
}

/// The test deployment's credentials (made on first use).
pub fn credentials() -> &'static Credentials {
    static CREDENTIALS: OnceLock<Credentials> = OnceLock::new();
    CREDENTIALS.get_or_init(|| {
        // Beside the binaries (so `cargo clean` takes them), one directory
        // per test process; those of processes an hour gone are removed.
        let target = binary("tweezer").parent().expect("a target directory");
        let parent = target.join("test-credentials");
        if let Ok(entries) = std::fs::read_dir(&parent) {
            for entry in entries.flatten() {
                let old = entry
                    .metadata()
                    .and_then(|m| m.modified())
                    .is_ok_and(|t| t.elapsed().is_ok_and(|age| age > Duration::from_secs(3600)));
                if old {
                    let _ = std::fs::remove_dir_all(entry.path());
                }
            }
        }
        let dir = parent.join(std::process::id().to_string());
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("a credentials directory");
        let d = dir.to_str().expect("a UTF-8 path");
        let tweezer = |args: &[&str]| stdout_of(&run("tweezer", args));
        tweezer(&["cert", "ca", "--out", d, "--days", "2"]);
        for name in ["server", "client"] {
            tweezer(&[
                "cert", "issue", "--ca", d, "--name", name, "--host", "127.0.0.1", "--host",
                "localhost", "--out", d, "--days", "2",
            ]);
        }
        for (role, name, tokens) in [
            ("read", "read", "tokens"),
            ("actor", "actor", "tokens"),
            ("control", "control", "tokens"),
            ("control", "stranger", "other-tokens"),
        ] {
            let out = format!("{d}/{name}.token");
            let tokens = format!("{d}/{tokens}");
            tweezer(&[
                "token", "new", "--role", role, "--name", name, "--tokens", &tokens, "--out", &out,
            ]);
        }
        let server = "cert = \"server.crt\"\nkey = \"server.key\"\ntokens = \"tokens\"\nca = \"ca.crt\"\ntoken_file = \"read.token\"\n";
        let files = [
            ("server", server.to_string()),
            ("server-mtls", format!("{server}require_client_cert = true\n")),
            ("server-plain", "plaintext = true\ntokens = \"tokens\"\n".into()),
            ("read-plain", "plaintext = true\ntoken_file = \"read.token\"\n".into()),
            ("probe", "ca = \"ca.crt\"\n".into()),
            (
                "control-cert",
                "ca = \"ca.crt\"\ntoken_file = \"control.token\"\ncert = \"client.crt\"\nkey = \"client.key\"\n".into(),
            ),
        ];
        for (name, text) in files {
            write(&dir.join(format!("{name}.toml")), &text);
        }
        for name in ["read", "actor", "control", "stranger"] {
            write(
                &dir.join(format!("{name}.toml")),
                &format!("ca = \"ca.crt\"\ntoken_file = \"{name}.token\"\n"),
            );
        }
        // Not a security file, but made once with them: agents started
        // from several test threads read it.
        write(&dir.join("agent-control.toml"), AGENT_CONTROL);
        Credentials { dir }
    })
}

/// Starts `learner serve` with `args` and the test deployment's server
/// security file; returns it, once it listens, and the address it listens
/// on.
pub fn start_learner(args: &[&str]) -> (Child, String) {
    let security = credentials().file("server");
    let mut all = vec!["serve", "--security", &security];
    all.extend_from_slice(args);
    start_service("learner", &all, None)
}

/// Starts `hardware-agent serve --twin --greedy` on a free loopback port
/// with the test deployment's server security file, [`AGENT_CONTROL`] and
/// `args` (`--rate`, `--records`, ...), its standard error to `log` if
/// given; returns it, once it listens, and the address it listens on.
pub fn start_agent(args: &[&str], log: Option<&Path>) -> (Child, String) {
    let config = credentials().dir.join("agent-control.toml");
    start_configured_agent(config.to_str().expect("a UTF-8 path"), args, log)
}

/// [`start_agent`] with the config file `config` instead of
/// [`AGENT_CONTROL`]'s.
pub fn start_configured_agent(config: &str, args: &[&str], log: Option<&Path>) -> (Child, String) {
    let security = credentials().file("server");
    let mut all = agent_serve_args(config, &security);
    all.extend_from_slice(args);
    start_service("hardware-agent", &all, log)
}

/// The arguments of `hardware-agent serve --twin --greedy` on a free
/// loopback port with the config file `config` and the security file
/// `security`.
pub fn agent_serve_args<'a>(config: &'a str, security: &'a str) -> Vec<&'a str> {
    vec![
        "--config",
        config,
        "serve",
        "--twin",
        "--greedy",
        "--listen",
        "127.0.0.1:0",
        "--security",
        security,
    ]
}

/// Starts `learner serve` with the security file `security`, the config
/// file `config` and the run directory `run_dir`, its standard error to
/// `log` if given; returns it, once it listens, and its address.
pub fn start_learner_with(
    security: &str,
    config: &str,
    run_dir: &Path,
    log: Option<&Path>,
) -> (Child, String) {
    let run_dir = run_dir.to_str().expect("a UTF-8 path");
    let args = [
        "serve",
        "--security",
        security,
        "--config",
        config,
        "--run-dir",
        run_dir,
    ];
    start_service("learner", &args, log)
}

/// A channel to the service at `addr` (`host:port`) as the security file
/// `name` says.
pub async fn connect(addr: &str, name: &str) -> tweezer_rpc::AuthChannel {
    credentials()
        .client(name)
        .connect(addr, Duration::from_secs(10))
        .await
        .unwrap_or_else(|e| panic!("cannot connect to {addr}: {e}"))
}

/// The longest a service may take to start listening: a learner that
/// resumes a run reads its checkpoint and replay first.
pub const START_LIMIT: Duration = Duration::from_secs(120);

/// Starts binary `bin` with `args` (its standard error to `log`, if
/// given), waits (up to [`START_LIMIT`]) for its first stdout line,
/// `<bin> listening on ADDR`, and returns it with ADDR.
pub fn start_service(bin: &str, args: &[&str], log: Option<&Path>) -> (Child, String) {
    start_service_with_env(bin, args, &[], log)
}

/// [`start_service`] with `vars` added to the process's environment.
pub fn start_service_with_env(
    bin: &str,
    args: &[&str],
    vars: &[(&str, &str)],
    log: Option<&Path>,
) -> (Child, String) {
    let mut command = Command::new(binary(bin));
    command.args(args).envs(vars.iter().copied());
    spawn_service(bin, command, log)
}

/// [`start_service`] with the process's open-files limit (soft and hard)
/// set to `limit`, as a default login or service manager might leave it.
pub fn start_service_with_open_files(bin: &str, args: &[&str], limit: u64) -> (Child, String) {
    let mut command = Command::new("sh");
    command
        .args(["-c", &format!("ulimit -n {limit} && exec \"$0\" \"$@\"")])
        .arg(binary(bin))
        .args(args);
    spawn_service(bin, command, None)
}

/// [`start_service`] for a `command` that runs binary `bin`.
pub fn spawn_service(bin: &str, command: Command, log: Option<&Path>) -> (Child, String) {
    spawn_service_then(bin, command, log, |_| {})
}

/// [`spawn_service`], with `then` called on the process as soon as it is
/// started, before it listens (to signal it during start-up, say).
pub fn spawn_service_then(
    bin: &str,
    mut command: Command,
    log: Option<&Path>,
    then: impl FnOnce(&Child),
) -> (Child, String) {
    let stderr = match log {
        Some(path) => Stdio::from(
            std::fs::File::create(path).unwrap_or_else(|e| panic!("cannot create the log: {e}")),
        ),
        None => Stdio::null(),
    };
    let mut child = command
        .stdout(Stdio::piped())
        .stderr(stderr)
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {bin}: {e}"));
    then(&child);
    let stdout = child.stdout.take().expect("stdout is piped");
    let (sender, first) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let read = BufReader::new(stdout).read_line(&mut line);
        let _ = sender.send(read.map(|_| line));
    });
    let line = match first.recv_timeout(START_LIMIT) {
        Ok(Ok(line)) => line,
        Ok(Err(e)) => panic!("{bin} writes its address: {e}"),
        Err(_) => {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{bin} wrote no address within {START_LIMIT:?}")
        }
    };
    let addr = line
        .trim()
        .strip_prefix(&format!("{bin} listening on "))
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .to_string();
    (child, addr)
}

/// A child process killed if dropped before it is stopped, so that a
/// failing test leaves nothing running.
pub struct Running(Option<Child>);

impl Running {
    /// Guards `child`.
    pub fn new(child: Child) -> Self {
        Self(Some(child))
    }

    /// The process.
    pub fn child(&self) -> &Child {
        self.0.as_ref().expect("running until stopped")
    }

    /// SIGTERM, then the exit status and what is left of standard output.
    pub fn stop(mut self) -> (ExitStatus, String) {
        stop(self.0.take().expect("not stopped yet"))
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        if let Some(mut child) = self.0.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Sends signal `name` (`TERM`, `INT`, ...) to `child`.
pub fn signal(child: &Child, name: &str) {
    let sent = Command::new("kill")
        .args([&format!("-{name}"), &child.id().to_string()])
        .status()
        .expect("kill runs");
    assert!(sent.success(), "kill -{name} failed");
}

/// SIGTERM, then (within two minutes, [`output_within`]) the exit status
/// and what is left of standard output.
pub fn stop(child: Child) -> (ExitStatus, String) {
    signal(&child, "TERM");
    let output = output_within(child, Duration::from_secs(120), "the stopped process");
    (
        output.status,
        String::from_utf8(output.stdout).expect("utf-8 output"),
    )
}

/// The status of the learner at `addr`, asked with the security file
/// `name`'s token.
pub async fn learner_status(addr: &str, name: &str) -> Result<pb::LearnerStatus, String> {
    let channel = credentials()
        .client(name)
        .connect(addr, Duration::from_secs(10))
        .await
        .map_err(|e| e.to_string())?;
    tweezer_rpc::learner_status(&mut LearnerClient::new(channel))
        .await
        .map_err(|e| e.to_string())
}

/// The learner's status, or None while it cannot be reached.
pub fn status(runtime: &tokio::runtime::Runtime, addr: &str) -> Option<pb::LearnerStatus> {
    runtime.block_on(learner_status(addr, "read")).ok()
}

/// Polls the learner at `addr` until `done` holds; panics naming `what`
/// after `limit`.
pub fn wait_for_learner(
    runtime: &tokio::runtime::Runtime,
    addr: &str,
    what: &str,
    limit: Duration,
    done: impl Fn(&pb::LearnerStatus) -> bool,
) -> pb::LearnerStatus {
    let deadline = Instant::now() + limit;
    let mut last = None;
    loop {
        if let Some(s) = status(runtime, addr) {
            if done(&s) {
                return s;
            }
            last = Some(s);
        }
        assert!(
            Instant::now() < deadline,
            "never {what}; last status {last:?}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The hardware agent's state in `status`.
pub fn agent_state(status: &pb::AgentStatus) -> pb::AgentState {
    pb::AgentState::try_from(status.state).unwrap()
}

/// The hardware agent's status, now.
pub async fn agent_status(
    client: &mut HardwareAgentClient<tweezer_rpc::AuthChannel>,
) -> pb::AgentStatus {
    client
        .get_status(pb::AgentStatusRequest {})
        .await
        .unwrap()
        .into_inner()
}

/// Polls the hardware agent every 20 ms until its status satisfies `done`
/// and returns that status; panics with the last one, saying that it
/// never reached `what`, after `within`.
pub async fn wait_for_agent(
    client: &mut HardwareAgentClient<tweezer_rpc::AuthChannel>,
    what: &str,
    within: Duration,
    done: impl Fn(&pb::AgentStatus) -> bool,
) -> pb::AgentStatus {
    let deadline = Instant::now() + within;
    loop {
        let status = agent_status(client).await;
        if done(&status) {
            return status;
        }
        assert!(
            Instant::now() < deadline,
            "the agent never reached {what} within {within:?}: {status:?}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// [`wait_for_agent`] until the agent's state is `want`.
pub async fn wait_for_agent_state(
    client: &mut HardwareAgentClient<tweezer_rpc::AuthChannel>,
    want: pb::AgentState,
    within: Duration,
) -> pb::AgentStatus {
    wait_for_agent(client, &format!("{want:?}"), within, |status| {
        agent_state(status) == want
    })
    .await
}

/// A one-command train file in [`TINY_ENV`]: a learner that learns from
/// the first few hundred steps, actors of 4 environments, `train` (a
/// `[train]` table and anything after it).
pub fn tiny_train_file(train: &str) -> String {
    format!(
        "{TINY_ENV}\n[learner]\nuniform_steps = 300\n\
         [learner.limiter]\nmin_size = 200\nupdates_per_insert = 0.25\n\
         [learner.snapshots]\nevery_updates = 50\n\
         [actor]\nenvs = 4\nbatch_steps = 50\n{train}"
    )
}

/// `experiment train` of the train file `train` into `out`, with a JSON
/// summary and this workspace's learner and actor.
pub fn experiment_train(train: &str, out: &Path) -> Command {
    let mut command = Command::new(binary("experiment"));
    command
        .args(["--config", train, "train", "--json", "--out"])
        .arg(out)
        .arg("--learner-bin")
        .arg(binary("learner"))
        .arg("--actor-bin")
        .arg(binary("actor"));
    command
}

/// A loopback port free at the time of the call.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port()
}

/// Writes `text` to `path`; returns the path as a string for arguments.
pub fn write(path: &Path, text: &str) -> String {
    std::fs::write(path, text).unwrap_or_else(|e| panic!("cannot write {}: {e}", path.display()));
    path.to_str().expect("a UTF-8 path").to_string()
}

/// Runs `program` with `args` (within [`RUN_LIMIT`]); its standard output,
/// or a panic with what it printed.
pub fn check(program: &Path, args: &[&str]) -> String {
    let output = output_of(Command::new(program).args(args));
    assert!(
        output.status.success(),
        "{} {args:?} failed:\n{}{}",
        program.display(),
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

/// A fresh Python virtual environment in `dir` with the packages pinned in
/// `tests/python/<requirements>` installed from PyPI; its `bin` directory.
pub fn python_venv(dir: &Path, requirements: &str) -> PathBuf {
    let venv = dir.join("venv");
    let made = Command::new("python3")
        .args(["-m", "venv"])
        .arg(&venv)
        .output()
        .unwrap_or_else(|e| {
            panic!("this test needs python3 ({e}): install it (Debian: apt-get install python3 python3-venv)")
        });
    assert!(
        made.status.success(),
        "this test needs Python's venv module: install it (Debian: apt-get install python3-venv); python3 -m venv said:\n{}",
        String::from_utf8_lossy(&made.stderr)
    );
    let requirements = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("python")
        .join(requirements);
    let installed = output_of(
        Command::new(venv.join("bin/python"))
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
                "-r",
            ])
            .arg(&requirements),
    );
    assert!(
        installed.status.success(),
        "this test installs {} from PyPI, which it could not reach (or set PIP_INDEX_URL to a mirror); pip said:\n{}",
        requirements.display(),
        String::from_utf8_lossy(&installed.stderr)
    );
    venv.join("bin")
}
