//! `experiment train`: one command trains an agent. It writes a run directory,
//! starts `learner serve` and K actor processes on loopback (real processes,
//! real gRPC), shows progress from the learner's status, stops them in order
//! (actors, then the learner with its final checkpoint) at the time limit or
//! on SIGINT/SIGTERM, and ends with the report of the run: the best
//! snapshot evaluated on held-out seeds next to greedy and the planner, and
//! the figures.
//! A file with a `[sweep]` trains each of its runs in turn, then reports
//! over all of them.

use crate::processes::{ActorLauncher, Process, sibling_binary, start_learner, stop_actors};
use crate::progress::{self, Progress};
use crate::report::{self, Report, ReportOptions};
use crate::train_file::TrainFile;
use anyhow::{Context, bail};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use tweezer_gym::SplitMix64;
use tweezer_learner::config::LearnerFile;
use tweezer_learner::persistence::durable_write::write_bytes_atomic;
use tweezer_learner::persistence::run_dir::RunDir;
use tweezer_learner::persistence::run_log::RunLog;
use tweezer_process::StopSignals;
use tweezer_proto::pb::LearnerStatus;
use tweezer_proto::pb::learner_client::LearnerClient;
use tweezer_rpc::{AuthChannel, ClientSecurity, LoopbackCredentials, Security, learner_status};

/// How often the learner's status is polled.
const POLL: Duration = Duration::from_secs(1);
/// Restarts of one actor after which the run gives up.
const MAX_RESTARTS: u32 = 5;

/// What to run.
#[derive(Debug)]
pub struct TrainOptions {
    /// The run's settings (ignored when resuming: the run's own are used).
    pub file: TrainFile,
    /// The run directory.
    pub out: PathBuf,
    /// Continue the run in `out` from its newest checkpoint.
    pub resume: bool,
    /// Minutes of training instead of `train.minutes`.
    pub minutes: Option<f64>,
    /// The learner binary, if not next to this one.
    pub learner_bin: Option<PathBuf>,
    /// The actor binary, if not next to this one.
    pub actor_bin: Option<PathBuf>,
}

/// The binaries a run starts.
struct Binaries {
    learner: PathBuf,
    actor: PathBuf,
}

/// How the run went: printed at the end, and a `train` line of its metrics.
#[derive(Debug, Serialize)]
pub struct TrainSummary {
    /// The run directory.
    pub run_dir: PathBuf,
    /// Whether a signal ended it before its time limit.
    pub interrupted: bool,
    /// Seconds of training in this session.
    pub seconds: f64,
    /// Steps stored and updates made in this session.
    pub steps: u64,
    /// Updates made in this session.
    pub updates: u64,
    /// Steps stored per second of this session, all actors together.
    pub end_to_end_steps_per_sec: f64,
    /// Updates per second of this session.
    pub updates_per_sec: f64,
    /// Actor restarts after unexpected exits.
    pub actor_restarts: u32,
}

/// What a training command did: its runs (one, or a sweep's), and the
/// report over them.
#[derive(Debug, Serialize)]
pub struct TrainOutcome {
    /// Each run's summary, in the order they ran.
    pub runs: Vec<TrainSummary>,
    /// The report (absent when stopped again while it was being made).
    pub report: Option<Report>,
}

/// Runs training as `options` say: one run, or each run of the file's
/// sweep one after another (a signal ends the sweep); then the report over
/// the runs into `<out>/report`.
pub fn run(options: TrainOptions) -> anyhow::Result<TrainOutcome> {
    let out = &options.out;
    let runs: Vec<(PathBuf, TrainFile)> = if options.resume {
        let file = TrainFile::load(&RunDir::new(out).train_file())
            .with_context(|| format!("cannot resume {}", out.display()))?;
        if !file.sweep.is_empty() {
            bail!(
                "{} is a sweep: resume its runs one by one (`experiment train --resume --out {0}/<run>`)",
                out.display()
            );
        }
        vec![(out.clone(), file)]
    } else if options.file.sweep.is_empty() {
        vec![(out.clone(), prepare(options.file.clone(), out)?)]
    } else {
        let runs = options.file.sweep.runs(&options.file)?;
        claim(out)?;
        write_file(&RunDir::new(out).train_file(), &options.file.to_toml())?;
        runs.into_iter()
            .map(|run| {
                let dir = out.join(&run.name);
                prepare(run.file, &dir).map(|file| (dir, file))
            })
            .collect::<anyhow::Result<_>>()?
    };
    let binaries = Binaries {
        learner: sibling_binary("learner", options.learner_bin.as_deref())?,
        actor: sibling_binary("actor", options.actor_bin.as_deref())?,
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    runtime.block_on(async {
        let mut signals = StopSignals::install(&tokio::runtime::Handle::current())?;
        let mut summaries = Vec::new();
        for (k, (dir, file)) in runs.iter().enumerate() {
            if runs.len() > 1 {
                eprintln!("run {} of {}: {}", k + 1, runs.len(), file.train.label);
            }
            let minutes = options.minutes.unwrap_or(file.train.minutes);
            if !(minutes.is_finite() && minutes >= 0.0) {
                bail!("--minutes must be finite and >= 0, got {minutes}");
            }
            let limit = (minutes > 0.0).then(|| Duration::from_secs_f64(minutes * 60.0));
            let summary =
                supervise(file, dir, options.resume, limit, &binaries, &mut signals).await?;
            let interrupted = summary.interrupted;
            summaries.push(summary);
            if interrupted {
                break;
            }
        }
        let dirs: Vec<PathBuf> = summaries.iter().map(|s| s.run_dir.clone()).collect();
        let report =
            final_report(&runs[0].1, dirs, RunDir::new(out).report(), &mut signals).await?;
        Ok(TrainOutcome {
            runs: summaries,
            report,
        })
    })
}

/// The report over `runs`, unless a signal comes first.
async fn final_report(
    file: &TrainFile,
    runs: Vec<PathBuf>,
    out: PathBuf,
    signals: &mut StopSignals,
) -> anyhow::Result<Option<Report>> {
    eprintln!("evaluating the best snapshots and drawing the report (Ctrl-C skips this)");
    let options = ReportOptions {
        seeds: file.train.eval_seeds()?.0,
        picture_seeds: file.train.picture_seeds()?.0,
        validation_seeds: file.train.validation_seeds()?.map(|s| s.0),
        batch: file.train.eval_batch,
    };
    let dirs = runs
        .iter()
        .map(|d| d.display().to_string())
        .collect::<Vec<_>>()
        .join(" ");
    let reporting = tokio::task::spawn_blocking(move || report::write(&runs, &out, &options));
    tokio::select! {
        signal = signals.recv() => {
            eprintln!("{signal}: report skipped; run `experiment report {dirs}` later");
            Ok(None)
        }
        written = reporting => {
            let report = written??;
            log_evaluations(&report)?;
            Ok(Some(report))
        }
    }
}

/// Each run's held-out evaluation as an `eval` line of its run log (and so
/// TensorBoard scalars), at the training step of the snapshot evaluated.
fn log_evaluations(report: &Report) -> anyhow::Result<()> {
    #[derive(Serialize)]
    struct EvalLine<'a> {
        updates: u64,
        snapshot: &'a str,
        seeds: &'a str,
        #[serde(flatten)]
        summary: &'a tweezer_gym::EvalSummary,
    }
    for row in report.rows.iter().filter(|r| !r.run.is_empty()) {
        let info = std::fs::read(&row.snapshot)
            .ok()
            .and_then(|bytes| tweezer_nets::read_info(&bytes).ok());
        let run = RunDir::new(Path::new(&row.run));
        RunLog::append(&run.run_log(), "experiment")
            .with_context(|| format!("cannot open {}", run.run_log().display()))?
            .write(
                "eval",
                EvalLine {
                    updates: info.map_or(0, |i| i.training_step),
                    snapshot: &row.policy,
                    seeds: &report.seeds,
                    summary: &row.summary,
                },
            );
    }
    Ok(())
}

/// Refuses a directory that already holds a run.
fn claim(out: &Path) -> anyhow::Result<()> {
    let run = RunDir::new(out);
    if run.train_file().exists() || run.config().exists() {
        bail!(
            "{} already holds a run: continue it with `experiment train --resume --out {0}`, or choose another --out",
            out.display()
        );
    }
    std::fs::create_dir_all(out)
        .with_context(|| format!("cannot create run directory {}", out.display()))
}

fn write_file(path: &Path, text: &str) -> anyhow::Result<()> {
    write_bytes_atomic(path, text.as_bytes())
        .with_context(|| format!("cannot write {}", path.display()))
}

/// A fresh run directory with the run's files: `train.toml` (everything),
/// `config.toml` (the learner's), `actor.toml` (the actors').
fn prepare(mut file: TrainFile, out: &Path) -> anyhow::Result<TrainFile> {
    claim(out)?;
    file.learner.run_dir = out.to_path_buf();
    let learner = LearnerFile {
        env: file.env.clone(),
        learner: file.learner.clone(),
    };
    let mut actor = toml::Table::new();
    actor.insert("env".into(), toml::Value::try_from(&file.env)?);
    actor.insert("actor".into(), toml::Value::Table(file.actor.clone()));
    let run = RunDir::new(out);
    write_file(&run.train_file(), &file.to_toml())?;
    write_file(&run.config(), &learner.to_toml())?;
    write_file(&run.actor_config(), &toml::to_string(&actor)?)?;
    Ok(file)
}

/// Why training stopped.
enum Ending {
    TimeUp,
    /// The learner made its `max_updates`.
    UpdatesMade,
    Signal(&'static str),
}

/// Runs one segment of training in `out` (a new run, or resuming it)
/// until `limit` passes or a stop signal comes: the learner, its actors
/// restarted when they exit, progress from the learner's status; then
/// stops them all, the learner last with its final checkpoint.
async fn supervise(
    file: &TrainFile,
    out: &Path,
    resume: bool,
    limit: Option<Duration>,
    binaries: &Binaries,
    signals: &mut StopSignals,
) -> anyhow::Result<TrainSummary> {
    let run = RunDir::new(out);
    let logs = run.logs();
    std::fs::create_dir_all(&logs).with_context(|| format!("cannot create {}", logs.display()))?;
    let credentials = LoopbackCredentials::provision(&run.security())?;
    let (learner, addr) =
        start_learner(&binaries.learner, &run, resume, &credentials.learner).await?;
    tracing::info!(
        learner = %addr,
        "learner listening; watch it with `tweezer --security {} learner --learner {addr} status --watch 2`",
        credentials.read.display()
    );
    let reader = ClientSecurity::load(&Security::load(Some(&credentials.read))?)?;
    let mut client = LearnerClient::new(
        reader
            .connect(&addr.to_string(), Duration::from_secs(10))
            .await
            .context("cannot connect to the learner")?,
    );
    let first = status(&mut client).await?;
    let launcher = ActorLauncher {
        binary: binaries.actor.clone(),
        config: run.actor_config(),
        learner: addr,
        security: credentials.actor.clone(),
        logs: logs.clone(),
    };
    // Each segment of a run and each restart draws other seeds.
    let session = first.steps_inserted.rotate_left(20);
    let actors = Actors::start(launcher, file.train.actors, file.learner.seed ^ session)?;
    let progress = Progress::new(limit);
    progress.say(&format!(
        "training in {} with {} actor(s){}; logs in {}",
        out.display(),
        file.train.actors,
        limit
            .map(|l| format!(" for {}", progress::clock(l)))
            .unwrap_or_default(),
        logs.display()
    ));
    let started = Instant::now();
    let mut running = Running {
        learner,
        actors,
        client,
        logs,
        progress,
        last: first.clone(),
    };
    let deadline = limit.map(|l| started + l);
    let ending = (running.watch(deadline, file.learner.max_updates, signals)).await?;
    let seconds = started.elapsed().as_secs_f64();
    let interrupted = running.stop(ending).await?;
    let last = running.last;
    let steps = last.steps_inserted.saturating_sub(first.steps_inserted);
    let updates = last.updates.saturating_sub(first.updates);
    let summary = TrainSummary {
        run_dir: out.to_path_buf(),
        interrupted,
        seconds,
        steps,
        updates,
        end_to_end_steps_per_sec: steps as f64 / seconds.max(1e-9),
        updates_per_sec: updates as f64 / seconds.max(1e-9),
        actor_restarts: running.actors.restarts(),
    };
    RunLog::append(&run.run_log(), "experiment")
        .with_context(|| format!("cannot open {}", run.run_log().display()))?
        .write("train", &summary);

    Ok(summary)
}

/// A training segment's processes while it runs.
struct Running {
    learner: Process,
    actors: Actors,
    client: LearnerClient<AuthChannel>,
    /// Where the processes' logs go.
    logs: PathBuf,
    progress: Progress,
    /// The learner's newest status.
    last: LearnerStatus,
}

impl Running {
    /// Watches the learner and its actors every [`POLL`] until `deadline`
    /// passes, the learner has made `max_updates` (when not 0) or a signal
    /// comes, restarting actors that exit and showing the learner's
    /// status. When the learner exits, or an actor fails too often, the
    /// rest are stopped and the error says why.
    async fn watch(
        &mut self,
        deadline: Option<Instant>,
        max_updates: u64,
        signals: &mut StopSignals,
    ) -> anyhow::Result<Ending> {
        let mut ticker = tokio::time::interval(POLL);
        loop {
            tokio::select! {
                signal = signals.recv() => return Ok(Ending::Signal(signal)),
                _ = ticker.tick() => {}
            }
            if deadline.is_some_and(|d| Instant::now() >= d) {
                return Ok(Ending::TimeUp);
            }
            if let Some(result) = self.learner.exited() {
                let _ = self.actors.stop().await;
                result?;
                bail!(
                    "the learner exited before training ended; see {}",
                    self.logs.join("learner.log").display()
                );
            }
            if let Err(e) = self.actors.restart_exited(&mut self.progress) {
                let _ = self.actors.stop().await;
                self.learner.stop(Duration::from_secs(3600)).await?;
                return Err(e);
            }
            match status(&mut self.client).await {
                Ok(s) => {
                    self.progress.update(&s);
                    let made = max_updates > 0 && s.updates >= max_updates;
                    self.last = s;
                    if made {
                        return Ok(Ending::UpdatesMade);
                    }
                }
                Err(e) => (self.progress).say(&format!("no status from the learner: {e:#}")),
            }
        }
    }

    /// Stops the actors, then the learner (which writes its final
    /// checkpoint), after reading the learner's status a last time;
    /// whether a signal (not the time limit) ended training.
    async fn stop(&mut self, ending: Ending) -> anyhow::Result<bool> {
        self.progress.finish();
        let (interrupted, why) = match ending {
            Ending::TimeUp => (false, "time is up"),
            Ending::UpdatesMade => (false, "the learner made its max_updates"),
            Ending::Signal(signal) => (true, signal),
        };
        eprintln!("{why}: stopping the actors, then the learner (final checkpoint)");
        if let Ok(s) = status(&mut self.client).await {
            self.last = s;
        }
        for error in self.actors.stop().await {
            eprintln!("{error:#}");
        }
        stop_learner(&mut self.learner).await?;
        Ok(interrupted)
    }
}

/// A run's actors, each restarted when it exits, up to [`MAX_RESTARTS`]
/// times.
struct Actors {
    launcher: ActorLauncher,
    running: Vec<Process>,
    restarts: Vec<u32>,
    /// What every actor's seed derives from.
    seed: u64,
}

impl Actors {
    /// Starts `count` actors with seeds derived from `seed`.
    fn start(launcher: ActorLauncher, count: usize, seed: u64) -> anyhow::Result<Self> {
        let mut actors = Self {
            launcher,
            running: Vec::with_capacity(count),
            restarts: vec![0; count],
            seed,
        };
        for k in 0..count {
            let process = actors.launcher.start(k, actors.seed_of(k))?;
            actors.running.push(process);
        }
        Ok(actors)
    }

    /// Actor `k`'s seed for its current start.
    fn seed_of(&self, k: usize) -> u64 {
        let restart = u64::from(self.restarts[k]) << 48;
        SplitMix64::derived(self.seed ^ restart, k as u64).next_u64()
    }

    /// Starts again every actor that exited, saying why; an error once one
    /// has failed more than [`MAX_RESTARTS`] times.
    fn restart_exited(&mut self, progress: &mut Progress) -> anyhow::Result<()> {
        for k in 0..self.running.len() {
            let Some(result) = self.running[k].exited() else {
                continue;
            };
            self.restarts[k] += 1;
            let why = (result.err().map(|e| e.to_string())).unwrap_or_else(|| "exited".into());
            if self.restarts[k] > MAX_RESTARTS {
                bail!(
                    "actor-{k} failed {} times; the last time: {why}",
                    self.restarts[k]
                );
            }
            progress.say(&format!("restarting actor-{k}: {why}"));
            self.running[k] = self.launcher.start(k, self.seed_of(k))?;
        }
        Ok(())
    }

    /// Restarts so far, over all actors.
    fn restarts(&self) -> u32 {
        self.restarts.iter().sum()
    }

    /// Stops every actor; the errors of those that did not stop cleanly.
    async fn stop(&mut self) -> Vec<anyhow::Error> {
        stop_actors(&mut self.running).await
    }
}

/// Asks the learner to stop and waits for its final checkpoint.
async fn stop_learner(learner: &mut Process) -> anyhow::Result<()> {
    learner.terminate();
    learner.wait().await
}

async fn status(client: &mut LearnerClient<AuthChannel>) -> anyhow::Result<LearnerStatus> {
    learner_status(client).await.context("GetStatus failed")
}
