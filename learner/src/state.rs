//! What the gRPC service and the training thread share: the table (the
//! replay and its rate limiter), the actor sessions, episode statistics,
//! the published snapshots, the training status and the operator's
//! requests. Actors' batches enter here through [`LearnerState::accept`],
//! decoded by the service: each is checked whole before any step touches
//! the replay.

use crate::ingest::batch::{Ack, ActorBatch, Refusal};
use crate::ingest::episodes::{Episode, Episodes};
use crate::ingest::limiter::{Limiter, LimiterState};
use crate::ingest::sessions::{SessionKey, Sessions};
use crate::ingest::status::{LearnerStatus, TrainingStatus};
use crate::ingest::table::{ReplayGuard, Table};
use crate::persistence::checkpoint::SessionState;
use crate::persistence::run_log::RunLog;
use crate::persistence::snapshots::Snapshots;
use crate::replay::Replay;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};
use std::time::Duration;
use tweezer_gym::{Planner, StepBounds, StepRecord};
use tweezer_rpc::{Histogram, latency_buckets};

/// The state a checkpoint takes of the shared parts, read consistently.
#[derive(Debug)]
pub struct Captured {
    /// The replay's bytes, when asked for.
    pub replay: Option<Vec<u8>>,
    /// Transitions inserted since the run began.
    pub steps_inserted: u64,
    /// Finished episodes.
    pub episodes: Episodes,
    /// Each session's last stored batch and replay source.
    pub actors: Vec<SessionState>,
}

/// The learner's shared state.
#[derive(Debug)]
pub struct LearnerState {
    table: Table,
    bounds: StepBounds,
    sessions: Mutex<Sessions>,
    episodes: Mutex<Episodes>,
    steps_inserted: AtomicU64,
    uniform_steps: u64,
    connected: AtomicU32,
    malformed: AtomicU64,
    duplicates: AtomicU64,
    snapshots: Option<Mutex<Snapshots>>,
    training: Mutex<TrainingStatus>,
    run_log: RunLog,
    stopping: tokio::sync::watch::Sender<bool>,
    /// An operator paused learning (updates stop; the limiter then holds
    /// actors back).
    paused: AtomicBool,
    /// An operator asked for a checkpoint now.
    checkpoint_wanted: AtomicBool,
    /// The newest checkpoint attempt, announced to whoever waits for one.
    checkpoints: tokio::sync::watch::Sender<Option<CheckpointOutcome>>,
    timings: Timings,
    /// Labels each arriving observation with its action, for the actor to
    /// imitate (`td3.imitation`).
    guide: Option<Planner>,
}

/// A checkpoint attempt: the file written, or why none could be.
pub type CheckpointOutcome = Result<std::path::PathBuf, String>;

/// Latency histograms, exposed as Prometheus metrics.
#[derive(Debug)]
pub struct Timings {
    /// Seconds per TD3 update.
    pub update_seconds: Histogram,
    /// Seconds from a batch's arrival to its acknowledgement, waits for
    /// the rate limiter included.
    pub batch_seconds: Histogram,
}

impl Default for Timings {
    fn default() -> Self {
        Self {
            update_seconds: Histogram::new(latency_buckets()),
            batch_seconds: Histogram::new(latency_buckets()),
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl LearnerState {
    /// Ingestion into `replay`, rate limited by `limiter` when given
    /// (without one, nothing is learned: ingest alone); no snapshots, no
    /// metrics, actors told to explore uniformly throughout.
    pub fn new(replay: Replay, limiter: Option<Limiter>, bounds: StepBounds) -> Self {
        Self {
            table: Table::new(replay, limiter),
            bounds,
            sessions: Mutex::new(Sessions::default()),
            episodes: Mutex::new(Episodes::default()),
            steps_inserted: AtomicU64::new(0),
            uniform_steps: u64::MAX,
            connected: AtomicU32::new(0),
            malformed: AtomicU64::new(0),
            duplicates: AtomicU64::new(0),
            snapshots: None,
            training: Mutex::new(TrainingStatus::default()),
            run_log: RunLog::discard(),
            stopping: tokio::sync::watch::Sender::new(false),
            paused: AtomicBool::new(false),
            checkpoint_wanted: AtomicBool::new(false),
            checkpoints: tokio::sync::watch::Sender::new(None),
            timings: Timings::default(),
            guide: None,
        }
    }

    /// Labels every arriving step's observation with `planner`'s action.
    pub fn with_guide(mut self, planner: Planner) -> Self {
        self.guide = Some(planner);
        self
    }

    /// The latency histograms.
    pub fn timings(&self) -> &Timings {
        &self.timings
    }

    /// Actors explore uniformly until `steps` transitions are inserted.
    pub fn with_uniform_steps(mut self, steps: u64) -> Self {
        self.uniform_steps = steps;
        self
    }

    /// Serves and publishes into `snapshots`.
    pub fn with_snapshots(mut self, snapshots: Snapshots) -> Self {
        self.snapshots = Some(Mutex::new(snapshots));
        self
    }

    /// Writes episode lines to `run_log`.
    pub fn with_run_log(mut self, run_log: RunLog) -> Self {
        self.run_log = run_log;
        self
    }

    /// Continues the counters a checkpoint captured.
    pub fn with_restored(
        self,
        steps_inserted: u64,
        episodes: Episodes,
        actors: &[SessionState],
    ) -> Self {
        self.steps_inserted.store(steps_inserted, Ordering::Relaxed);
        *lock(&self.episodes) = episodes;
        *lock(&self.sessions) = Sessions::restored(actors);
        self
    }

    /// The replay and its rate limiter.
    pub fn table(&self) -> &Table {
        &self.table
    }

    /// The replay, held for reading.
    pub fn replay(&self) -> ReplayGuard<'_> {
        self.table.replay()
    }

    /// What the rate limiter is doing; `None` without one.
    pub fn limiter_state(&self) -> Option<LimiterState> {
        self.table.limiter().map(|(_, state)| state)
    }

    /// The status, read now.
    pub fn status(&self) -> LearnerStatus {
        let (buffer_size, buffer_capacity) = {
            let replay = self.replay();
            (replay.len(), replay.capacity())
        };
        let (rolling, episodes) = {
            let episodes = self.episodes();
            (episodes.rolling(), episodes.finished())
        };
        let (latest_snapshot, best_snapshot) = self
            .snapshots()
            .map_or((0, 0), |s| (s.latest_version(), s.best_version()));
        let (known_actors, actors) = {
            let sessions = lock(&self.sessions);
            (sessions.len(), sessions.summaries())
        };
        LearnerStatus {
            steps_inserted: self.steps_inserted(),
            training: *self.training(),
            buffer_size,
            buffer_capacity,
            limiter: self.limiter_state(),
            connected_actors: self.connected(),
            rolling,
            episodes,
            latest_snapshot,
            best_snapshot,
            malformed_batches: self.malformed(),
            duplicate_batches: self.duplicates(),
            explore_uniformly: self.explore_uniformly(),
            paused: self.paused(),
            known_actors,
            actors,
        }
    }

    /// The snapshots, when this learner publishes any.
    pub fn snapshots(&self) -> Option<MutexGuard<'_, Snapshots>> {
        self.snapshots.as_ref().map(lock)
    }

    /// The run log.
    pub fn run_log(&self) -> &RunLog {
        &self.run_log
    }

    /// The bounds every step of an actor's batch must lie in.
    pub fn bounds(&self) -> &StepBounds {
        &self.bounds
    }

    /// Counts a batch refused as malformed before it reached [`Self::accept`]
    /// (it could not be decoded).
    pub fn count_malformed(&self) {
        self.malformed.fetch_add(1, Ordering::Relaxed);
    }

    /// Batches refused as malformed.
    pub fn malformed(&self) -> u64 {
        self.malformed.load(Ordering::Relaxed)
    }

    /// Batches acknowledged without storing because they were stored before.
    pub fn duplicates(&self) -> u64 {
        self.duplicates.load(Ordering::Relaxed)
    }

    /// Transitions inserted since the run began.
    pub fn steps_inserted(&self) -> u64 {
        self.steps_inserted.load(Ordering::Relaxed)
    }

    /// Actor streams open now.
    pub fn connected(&self) -> u32 {
        self.connected.load(Ordering::Relaxed)
    }

    /// A stream opened.
    pub fn stream_opened(&self) {
        self.connected.fetch_add(1, Ordering::Relaxed);
    }

    /// A stream closed; `session` is the session it was bound to, if any.
    pub fn stream_closed(&self, session: Option<&SessionKey>) {
        self.connected.fetch_sub(1, Ordering::Relaxed);
        if let Some(key) = session {
            lock(&self.sessions).close_stream(key);
        }
    }

    /// Episode statistics.
    pub fn episodes(&self) -> MutexGuard<'_, Episodes> {
        lock(&self.episodes)
    }

    /// Training status.
    pub fn training(&self) -> MutexGuard<'_, TrainingStatus> {
        lock(&self.training)
    }

    /// Whether actors should still act uniformly at random.
    pub fn explore_uniformly(&self) -> bool {
        self.steps_inserted() < self.uniform_steps
    }

    /// Tells waiting producers and open streams to give up: the learner is
    /// shutting down.
    pub fn stop(&self) {
        self.stopping.send_replace(true);
    }

    /// Pauses or resumes learning.
    pub fn set_paused(&self, paused: bool) {
        self.paused.store(paused, Ordering::SeqCst);
    }

    /// Whether an operator paused learning.
    pub fn paused(&self) -> bool {
        self.paused.load(Ordering::SeqCst)
    }

    /// Asks the trainer for a checkpoint now; the receiver sees it written,
    /// or why it could not be.
    pub fn request_checkpoint(&self) -> tokio::sync::watch::Receiver<Option<CheckpointOutcome>> {
        let mut written = self.checkpoints.subscribe();
        written.mark_unchanged();
        self.checkpoint_wanted.store(true, Ordering::SeqCst);
        written
    }

    /// Whether a checkpoint was asked for (the request is taken).
    pub fn take_checkpoint_request(&self) -> bool {
        self.checkpoint_wanted.swap(false, Ordering::SeqCst)
    }

    /// Announces a written checkpoint.
    pub fn checkpoint_written(&self, path: std::path::PathBuf) {
        self.checkpoints.send_replace(Some(Ok(path)));
    }

    /// Announces a checkpoint that could not be written, and why.
    pub fn checkpoint_failed(&self, reason: String) {
        self.checkpoints.send_replace(Some(Err(reason)));
    }

    /// Whether [`Self::stop`] was called.
    pub fn stopping(&self) -> bool {
        *self.stopping.borrow()
    }

    /// Resolves once [`Self::stop`] is called.
    pub async fn stopped(&self) {
        let mut stopping = self.stopping.subscribe();
        let _ = stopping.wait_for(|s| *s).await;
    }

    /// Reads what a checkpoint needs, the replay locked throughout so that
    /// the actors' sequence numbers match its contents.
    pub fn capture(&self, with_replay: bool) -> Captured {
        let replay = self.replay();
        let actors = lock(&self.sessions).saved();
        Captured {
            replay: with_replay.then(|| replay.encode()),
            steps_inserted: self.steps_inserted(),
            episodes: self.episodes().clone(),
            actors,
        }
    }

    /// The ack for a batch: its sequence, the newest snapshot, the phase.
    fn ack(&self, sequence: u64) -> Ack {
        Ack {
            sequence,
            snapshot_version: self.snapshots().map_or(0, |s| s.latest_version()),
            explore_uniformly: self.explore_uniformly(),
        }
    }

    /// Checks and stores one batch of the stream that `stream_session`
    /// identifies (set by the stream's first batch), waiting for the rate
    /// limiter. `token` names the caller's token: a session stays with the
    /// token that opened it. A batch stored before (same session, sequence
    /// not above the last stored; never in session 0) is acknowledged and
    /// not stored again. `closed` says the client went away: a producer
    /// waiting on back-pressure then gives up.
    pub fn accept(
        &self,
        batch: ActorBatch,
        stream_session: &mut Option<SessionKey>,
        token: Option<&str>,
        closed: impl Fn() -> bool,
    ) -> Result<Ack, Refusal> {
        let refuse = |reason: String| {
            self.count_malformed();
            Refusal::Malformed(reason)
        };
        let ActorBatch {
            actor,
            session,
            sequence,
            steps,
        } = batch;
        let key = (actor, session);
        match stream_session {
            Some(bound) if *bound != key => {
                return Err(refuse(format!(
                    "actor_id, session: `{}` session {} on a stream opened by `{}` session {}",
                    key.0, key.1, bound.0, bound.1
                )));
            }
            Some(_) => {}
            None => {
                lock(&self.sessions).open_stream(&key, token)?;
                *stream_session = Some(key.clone());
            }
        }
        if let Some((i, reason)) =
            (steps.iter().enumerate()).find_map(|(i, s)| Replay::admits(s).err().map(|e| (i, e)))
        {
            return Err(refuse(format!("steps[{i}]: {reason}")));
        }
        if lock(&self.sessions).stored_before(&key, sequence) {
            self.duplicates.fetch_add(1, Ordering::Relaxed);
            return Ok(self.ack(sequence));
        }
        // Labelled before the table is held: planning is slow beside a copy.
        let guides = self.guides(&steps);
        let give_up = || {
            if closed() {
                Some(Refusal::Closed)
            } else if self.stopping() {
                Some(Refusal::ShuttingDown)
            } else {
                None
            }
        };
        // One transaction: the limiter counts the batch only if it is
        // stored, so a duplicate found here costs the ratio nothing.
        let stored = self.table.insert(
            steps.len() as u64,
            Duration::from_millis(100),
            give_up,
            |replay| self.store(replay, &key, token, sequence, &steps, guides),
        )?;
        let Some(finished) = stored else {
            // Another stream of the same session stored it meanwhile.
            self.duplicates.fetch_add(1, Ordering::Relaxed);
            return Ok(self.ack(sequence));
        };
        for episode in finished {
            self.run_log.write("episode", episode);
        }
        Ok(self.ack(sequence))
    }

    /// The guide's action for each step's observation, when this learner
    /// has a guide.
    fn guides(&self, steps: &[StepRecord]) -> Vec<Option<[f32; 2]>> {
        match &self.guide {
            Some(planner) => {
                let mut planner = planner.clone();
                (steps.iter())
                    .map(|s| Some(planner.action(&s.observation).components()))
                    .collect()
            }
            None => vec![None; steps.len()],
        }
    }

    /// Stores a batch in `replay` (the table held) and accounts for it: the
    /// session's last sequence, steps and episodes; `None` when the session
    /// has stored it already.
    fn store(
        &self,
        replay: &mut Replay,
        key: &SessionKey,
        token: Option<&str>,
        sequence: u64,
        steps: &[StepRecord],
        guides: Vec<Option<[f32; 2]>>,
    ) -> Result<Option<Vec<Episode>>, Refusal> {
        let mut sessions = lock(&self.sessions);
        let Some(session) = sessions.claim(key, token, sequence)? else {
            return Ok(None);
        };
        let source = session.source();
        let mut episodes = self.episodes();
        let mut finished = Vec::new();
        for (step, guide) in steps.iter().zip(guides) {
            replay
                .insert_guided(source, step, guide)
                .expect("steps were checked against the replay's limits");
            finished.extend(episodes.step(source, step));
        }
        session.stored_batch(steps.len(), finished.len());
        self.steps_inserted
            .fetch_add(steps.len() as u64, Ordering::Relaxed);
        Ok(Some(finished))
    }
}
