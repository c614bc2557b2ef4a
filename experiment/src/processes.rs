//! The run's child processes: the learner (`learner serve`) and the
//! actors, each logging into the run directory's `logs/`.

use anyhow::{Context, bail};
use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;
use std::fs::File;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};
use tweezer_learner::persistence::run_dir::RunDir;

/// How long the learner may take to listen (building networks, reading a
/// checkpoint).
const LEARNER_START: Duration = Duration::from_secs(600);
/// How long an actor may take to stop after SIGTERM.
const ACTOR_STOP: Duration = Duration::from_secs(15);

/// A child process and the log its standard error goes to.
pub struct Process {
    /// What it is, for messages: `learner`, `actor-0`, ...
    pub name: String,
    child: Child,
    log: PathBuf,
}

impl Process {
    fn spawn(name: &str, mut command: Command, logs: &Path, stdout: Stdio) -> anyhow::Result<Self> {
        let log = logs.join(format!("{name}.log"));
        let stderr = File::options()
            .create(true)
            .append(true)
            .open(&log)
            .with_context(|| format!("cannot open {}", log.display()))?;
        let child = command
            .stdin(Stdio::null())
            .stdout(stdout)
            .stderr(stderr)
            .kill_on_drop(true)
            .spawn()
            .with_context(|| format!("cannot start the {name} process"))?;
        Ok(Self {
            name: name.into(),
            child,
            log,
        })
    }

    /// Sends SIGTERM: the process finishes what it is doing and exits.
    pub fn terminate(&self) {
        if let Some(id) = self.child.id().and_then(|id| i32::try_from(id).ok()) {
            let _ = kill(Pid::from_raw(id), Signal::SIGTERM);
        }
    }

    /// Waits for the process to exit; an error if it failed.
    pub async fn wait(&mut self) -> anyhow::Result<()> {
        let status = self.child.wait().await?;
        self.check(status)
    }

    /// Whether it has exited, and how (without waiting).
    pub fn exited(&mut self) -> Option<anyhow::Result<()>> {
        match self.child.try_wait() {
            Ok(Some(status)) => Some(self.check(status)),
            Ok(None) => None,
            Err(e) => Some(Err(e.into())),
        }
    }

    /// SIGTERM, then SIGKILL if it has not exited within `grace`.
    pub async fn stop(&mut self, grace: Duration) -> anyhow::Result<()> {
        self.terminate();
        match tokio::time::timeout(grace, self.child.wait()).await {
            Ok(status) => self.check(status?),
            Err(_) => {
                self.child.kill().await?;
                bail!("{} did not stop within {grace:?} and was killed", self.name)
            }
        }
    }

    fn check(&self, status: std::process::ExitStatus) -> anyhow::Result<()> {
        if status.success() {
            return Ok(());
        }
        let tail = log_tail(&self.log);
        bail!(
            "{} exited with {status}; the end of {}:\n{tail}",
            self.name,
            self.log.display()
        )
    }
}

/// The last lines of a log, for error messages.
fn log_tail(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(8)..].join("\n")
}

/// Starts `binary serve` for `run_dir` (fresh from its `config.toml`, or
/// resuming) on a free loopback port with the security file `security`;
/// returns it once it listens.
pub async fn start_learner(
    binary: &Path,
    run_dir: &RunDir,
    resume: bool,
    security: &Path,
) -> anyhow::Result<(Process, SocketAddr)> {
    let mut command = Command::new(binary);
    command
        .arg("serve")
        .args(["--listen", "127.0.0.1:0"])
        .arg("--security")
        .arg(security);
    if resume {
        command.arg("--resume").arg(run_dir.path());
    } else {
        command
            .arg("--config")
            .arg(run_dir.config())
            .arg("--run-dir")
            .arg(run_dir.path());
    }
    let mut learner = Process::spawn("learner", command, &run_dir.logs(), Stdio::piped())?;
    let stdout = learner.child.stdout.take().expect("stdout is piped");
    let mut lines = BufReader::new(stdout).lines();
    let first = tokio::time::timeout(LEARNER_START, lines.next_line()).await;
    let line = match first {
        Ok(Ok(Some(line))) => line,
        Ok(_) => {
            learner.wait().await?;
            bail!("the learner exited before listening")
        }
        Err(_) => bail!("the learner did not listen within {LEARNER_START:?}"),
    };
    let addr = line
        .strip_prefix("learner listening on ")
        .and_then(|a| a.parse().ok())
        .with_context(|| format!("unexpected first line from the learner: {line:?}"))?;
    Ok((learner, addr))
}

/// How to start actors.
pub struct ActorLauncher {
    /// The actor binary.
    pub binary: PathBuf,
    /// Their config file (`[env]` and `[actor]`).
    pub config: PathBuf,
    /// The learner's address.
    pub learner: SocketAddr,
    /// Their security file.
    pub security: PathBuf,
    /// Where their logs and reports go.
    pub logs: PathBuf,
}

impl ActorLauncher {
    /// Starts actor `index` with episode seed `seed`; its JSON report goes
    /// to `logs/actor-<index>.json`.
    pub fn start(&self, index: usize, seed: u64) -> anyhow::Result<Process> {
        let name = format!("actor-{index}");
        let report = self.logs.join(format!("{name}.json"));
        let stdout =
            File::create(&report).with_context(|| format!("cannot create {}", report.display()))?;
        let mut command = Command::new(&self.binary);
        command
            .arg("--config")
            .arg(&self.config)
            .arg("run")
            .arg("--security")
            .arg(&self.security)
            .args(["--learner", &self.learner.to_string()])
            .args(["--id", &name])
            .args(["--seed", &seed.to_string()]);
        Process::spawn(&name, command, &self.logs, stdout.into())
    }
}

/// Stops every actor: SIGTERM to all, then each gets [`ACTOR_STOP`].
pub async fn stop_actors(actors: &mut [Process]) -> Vec<anyhow::Error> {
    for actor in actors.iter() {
        actor.terminate();
    }
    let mut errors = Vec::new();
    for actor in actors.iter_mut() {
        if let Err(e) = actor.stop(ACTOR_STOP).await {
            errors.push(e);
        }
    }
    errors
}

/// The binary `name` (`learner`, `actor`): `explicit`, or the one next to
/// this binary.
pub fn sibling_binary(name: &str, explicit: Option<&Path>) -> anyhow::Result<PathBuf> {
    let path = match explicit {
        Some(path) => path.to_path_buf(),
        None => std::env::current_exe()
            .context("cannot find this experiment binary")?
            .with_file_name(format!("{name}{}", std::env::consts::EXE_SUFFIX)),
    };
    if !path.is_file() {
        bail!(
            "no {name} binary at {}: build it next to this one (`cargo build --release --locked`) or pass --{name}-bin",
            path.display()
        );
    }
    Ok(path)
}
