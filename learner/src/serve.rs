//! `learner serve`: the learner process. Builds the shared state (fresh or
//! from the newest valid checkpoint), serves gRPC (the `Learner` service,
//! health and reflection, behind TLS and tokens as the security file says),
//! trains on a thread of its own, and on SIGINT or
//! SIGTERM stops accepting, finishes the update in flight and writes a
//! final checkpoint.

use crate::config::LearnerFile;
use crate::ingest::limiter::Limiter;
use crate::ingest::metrics::prometheus;
use crate::ingest::service::LearnerService;
use crate::persistence::checkpoint::{Checkpoints, Loaded};
use crate::persistence::durable_write::{remove_leftovers, write_bytes_atomic};
use crate::persistence::run_dir::RunDir;
use crate::persistence::run_lock::RunLock;
use crate::persistence::run_log::RunLog;
use crate::persistence::snapshots::Snapshots;
use crate::replay::Replay;
use crate::state::LearnerState;
use crate::training::trainer::training;
use anyhow::{Context, bail};
use std::sync::Arc;
use tweezer_gym::{Planner, StepBounds};
use tweezer_rpc::{Listeners, Security, ServerSecurity, Stopping};

/// How long clients may take to hang up once the learner stops.
const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(3);

/// How `serve` treats the run directory `learner.run_dir`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Start {
    /// A new run: refused if the directory holds checkpoints.
    Fresh,
    /// Continue from the newest valid checkpoint: refused if there is none.
    Resume,
    /// Continue if the directory holds checkpoints, start a new run
    /// otherwise: for restarts by systemd, Slurm or Kubernetes.
    Auto,
}

/// Runs the learner until a signal stops it or training fails, starting
/// as `start` says. `security` says how it listens: checked before
/// anything starts.
pub fn serve(file: LearnerFile, start: Start, security: &Security) -> anyhow::Result<()> {
    let listener_security = ServerSecurity::load(security)?;
    let config = &file.learner;
    // Before the run directory is touched: a device this build lacks is
    // refused naming the cargo feature.
    let device = config.device.device()?;
    let run_dir = &RunDir::new(&config.run_dir);
    let _lock = open_run_dir(run_dir)?;
    let checkpoints = Checkpoints::open(&run_dir.checkpoints(), config.checkpoints.keep)?;
    let (resumed, snapshots) = start_run(&file, start, run_dir, &checkpoints)?;
    let shared = Arc::new(shared_state(&file, run_dir, resumed.as_ref(), snapshots)?);
    let needed = checkpoints.needed_snapshots();
    if let Some(mut snapshots) = shared.snapshots() {
        snapshots.pin(needed);
    }
    let mut trainer = training(
        &file,
        shared.clone(),
        checkpoints,
        resumed.as_ref(),
        &device,
    )?;
    drop(resumed);
    trainer.publish_first()?;

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        let listeners = Listeners::bind(
            (config.listen, "learner.listen"),
            (config.metrics_listen).map(|listen| (listen, "learner.metrics_listen")),
        )
        .await?;
        let (trained_tx, trained_rx) = tokio::sync::oneshot::channel();
        let trainer_shared = shared.clone();
        let training = std::thread::Builder::new()
            .name("training".into())
            .spawn(move || {
                let result = trainer.run();
                trainer_shared.stop();
                let _ = trained_tx.send(result);
            })?;
        tracing::info!(run_dir = %run_dir.path().display(), "training");
        let service = LearnerService::new(shared.clone())
            .with_max_message_bytes(config.max_message_bytes)
            .into_server();
        let stopping = Stopping {
            on_signal: "finishing the update in flight and writing a checkpoint",
            ends: shared.stopped(),
            then: || shared.stop(),
            grace: SHUTDOWN_GRACE,
        };
        let metrics = Arc::new(prometheus(shared.clone()));
        let served = listeners
            .serve("learner", listener_security, service, metrics, stopping)
            .await;
        shared.stop();
        let trained = trained_rx.await.unwrap_or_else(|_| {
            Err(anyhow::anyhow!(
                "the training thread ended without a result"
            ))
        });
        let _ = training.join();
        served?;
        trained
    })
}

/// Creates `run_dir` if need be and locks it for this process, then
/// removes the temporary files an interrupted write left there.
fn open_run_dir(run_dir: &RunDir) -> anyhow::Result<RunLock> {
    std::fs::create_dir_all(run_dir.path())
        .with_context(|| format!("cannot create run directory {}", run_dir.path().display()))?;
    let lock = RunLock::acquire(run_dir)?;
    for dir in [run_dir.path(), &run_dir.checkpoints(), &run_dir.snapshots()] {
        let removed =
            remove_leftovers(dir).with_context(|| format!("cannot clean {}", dir.display()))?;
        for path in removed {
            tracing::info!(path = %path.display(), "removed a temporary file an interrupted write left");
        }
    }
    Ok(lock)
}

/// The run as `start` says: resumed from the newest usable checkpoint
/// with its snapshots, or new (its config.toml written, no snapshot yet;
/// refused where checkpoints are already).
fn start_run(
    file: &LearnerFile,
    start: Start,
    run_dir: &RunDir,
    checkpoints: &Checkpoints,
) -> anyhow::Result<(Option<Loaded>, Snapshots)> {
    let keep = file.learner.snapshots.keep;
    let resume = match start {
        Start::Fresh => false,
        Start::Resume => true,
        Start::Auto => !checkpoints.list()?.is_empty(),
    };
    if resume {
        let (loaded, snapshots) = newest_checkpoint(checkpoints, run_dir, keep)?;
        return Ok((Some(loaded), snapshots));
    }
    if !checkpoints.list()?.is_empty() {
        bail!(
            "{} already holds a run's checkpoints: continue it with `learner serve --resume {0}`, or set another learner.run_dir",
            run_dir.path().display()
        );
    }
    write_bytes_atomic(&run_dir.config(), file.to_toml().as_bytes())
        .context("cannot write the run's config.toml")?;
    Ok((None, Snapshots::create(&run_dir.snapshots(), keep)?))
}

/// The newest checkpoint that reads back whole and whose snapshots read
/// back too, with its snapshots restored; says which were skipped.
fn newest_checkpoint(
    checkpoints: &Checkpoints,
    run_dir: &RunDir,
    keep: usize,
) -> anyhow::Result<(Loaded, Snapshots)> {
    let (usable, skipped) = checkpoints.newest_usable(|loaded| {
        Snapshots::restore(&run_dir.snapshots(), keep, &loaded.header.snapshots)
            .map_err(|e| format!("its snapshots do not read back: {e}"))
    })?;
    for error in &skipped {
        tracing::warn!(%error, "skipping an unusable checkpoint");
    }
    let (loaded, snapshots) = usable.with_context(|| {
        format!(
            "no usable checkpoint in {} ({} unusable)",
            run_dir.checkpoints().display(),
            skipped.len()
        )
    })?;
    tracing::info!(
        path = %loaded.path.display(),
        updates = loaded.header.updates,
        steps = loaded.header.steps_inserted,
        "resuming"
    );
    Ok((loaded, snapshots))
}

/// The replay, limiter, counters and `snapshots`: fresh, or as `resumed`
/// left them. The limiter counts from the replay as restored, so a restored
/// learner cannot wait on its own old counters.
fn shared_state(
    file: &LearnerFile,
    run_dir: &RunDir,
    resumed: Option<&Loaded>,
    snapshots: Snapshots,
) -> anyhow::Result<LearnerState> {
    let config = &file.learner;
    let replay = match resumed.and_then(|l| l.part("replay")) {
        Some(bytes) => Replay::decode(config.replay.clone(), bytes)?,
        None => Replay::new(config.replay.clone()),
    };
    let limiter = Limiter::new(config.limiter.clone());
    let run_log = RunLog::append(&run_dir.run_log(), "learner")
        .with_context(|| format!("cannot open {}", run_dir.run_log().display()))?;
    let shared = LearnerState::new(replay, Some(limiter), StepBounds::for_config(&file.env))
        .with_uniform_steps(config.uniform_steps)
        .with_snapshots(snapshots)
        .with_run_log(run_log);
    // The planner labels what the actor imitates.
    let shared = if config.td3.imitation > 0.0 {
        shared.with_guide(Planner::for_config(&file.env))
    } else {
        shared
    };
    Ok(match resumed {
        Some(l) => shared.with_restored(
            l.header.steps_inserted,
            l.header.episodes.clone(),
            &l.header.sessions,
        ),
        None => shared,
    })
}
