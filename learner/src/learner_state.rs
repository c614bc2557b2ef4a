//! What the gRPC service and the training thread share: the replay, the
//! rate limiter, the actors known by their ids, episode statistics, the
//! published snapshots and the training status. Actors' batches enter here,
//! decoded by the service: each is checked whole before any step touches the
//! replay.

use crate::episodes::{Episode, Episodes, Rolling};
use crate::limiter::{LimiterState, SharedLimiter};
use crate::replay::{Replay, Source};
use crate::run_log::RunLog;
use crate::snapshots::Snapshots;
use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tweezer_gym::{ObservationBounds, StepRecord};
use tweezer_rpc::{Histogram, latency_buckets};

/// What training reports for status.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TrainingStatus {
    /// TD3 updates made.
    pub updates: u64,
    /// Recent mean critic loss.
    pub critic_loss: f64,
    /// Recent mean actor loss.
    pub actor_loss: f64,
    /// Recent mean Q of the sampled actions.
    pub mean_q: f64,
    /// Transitions inserted per second, recently.
    pub insert_rate: f64,
    /// Transitions sampled per second, recently.
    pub sample_rate: f64,
}

/// One batch of an actor's steps, decoded at the service edge.
#[derive(Clone, Debug, PartialEq)]
pub struct ActorBatch {
    /// The actor's id.
    pub actor: String,
    /// Its sequence number among the actor's batches.
    pub sequence: u64,
    /// The steps, in the order they were taken.
    pub steps: Vec<StepRecord>,
}

/// The answer to a stored (or already stored) batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Ack {
    /// The batch's sequence number.
    pub sequence: u64,
    /// The newest snapshot's version (0: none).
    pub snapshot_version: u64,
    /// Whether the actor should still act uniformly at random.
    pub explore_uniformly: bool,
}

/// Why a batch was not stored.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    /// The batch is malformed; the reason names the field.
    #[error("{0}")]
    Malformed(String),
    /// The actor went away while the batch waited for the rate limiter.
    #[error("the actor closed its stream")]
    Closed,
    /// The learner is stopping.
    #[error("the learner is shutting down")]
    ShuttingDown,
}

/// The learner's status, as GetStatus and the Prometheus metrics show it.
#[derive(Clone, Debug, PartialEq)]
pub struct LearnerStatus {
    /// Transitions inserted since the run began.
    pub steps_inserted: u64,
    /// What training reports.
    pub training: TrainingStatus,
    /// Transitions in the replay.
    pub buffer_size: usize,
    /// The replay's capacity.
    pub buffer_capacity: usize,
    /// What the rate limiter is doing; `None` while learning is paused.
    pub limiter: Option<LimiterState>,
    /// Actor streams open now.
    pub connected_actors: u32,
    /// Means over the recent episodes.
    pub rolling: Rolling,
    /// Episodes finished since the run began.
    pub episodes: u64,
    /// The newest snapshot's version (0: none).
    pub latest_snapshot: u64,
    /// The best snapshot's version (0: none).
    pub best_snapshot: u64,
    /// Batches refused as malformed.
    pub malformed_batches: u64,
    /// Batches acknowledged without storing because they were stored before.
    pub duplicate_batches: u64,
    /// Whether actors should still act uniformly at random.
    pub explore_uniformly: bool,
    /// Whether an operator paused learning.
    pub paused: bool,
    /// Every actor heard from, by id.
    pub actors: Vec<ActorSummary>,
}

/// An actor the learner has heard from.
#[derive(Clone, Copy, Debug)]
struct KnownActor {
    source: Source,
    /// The last batch stored.
    last_sequence: Option<u64>,
    /// Open streams bound to it.
    streams: u32,
    /// Steps stored and episodes finished since this process started.
    steps: u64,
    episodes: u64,
    /// When its last batch was stored.
    last_stored: Option<Instant>,
}

impl KnownActor {
    fn new(source: Source, last_sequence: Option<u64>) -> Self {
        Self {
            source,
            last_sequence,
            streams: 0,
            steps: 0,
            episodes: 0,
            last_stored: None,
        }
    }
}

/// One actor, as the learner sees it.
#[derive(Clone, Debug, PartialEq)]
pub struct ActorSummary {
    /// Its id.
    pub id: String,
    /// Open streams bound to it.
    pub streams: u32,
    /// Steps stored from it since this process started.
    pub steps: u64,
    /// Episodes it finished since this process started.
    pub episodes: u64,
    /// Seconds since its last stored batch (None: none since start).
    pub idle_seconds: Option<f64>,
    /// Its last stored batch's sequence number.
    pub last_sequence: Option<u64>,
}

/// The state a checkpoint takes of the shared parts, read consistently.
#[derive(Debug)]
pub struct Captured {
    /// The replay's bytes, when asked for.
    pub replay: Option<Vec<u8>>,
    /// Transitions inserted since the run began.
    pub steps_inserted: u64,
    /// Finished episodes.
    pub episodes: Episodes,
    /// Each actor's last stored batch.
    pub actors: BTreeMap<String, u64>,
}

/// The learner's shared state.
#[derive(Debug)]
pub struct LearnerState {
    replay: Mutex<Replay>,
    /// `None` while learning is paused: inserts are not rate limited.
    limiter: Option<SharedLimiter>,
    bounds: ObservationBounds,
    actors: Mutex<HashMap<String, KnownActor>>,
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
    /// The newest checkpoint written, announced to whoever waits for one.
    checkpoints: tokio::sync::watch::Sender<Option<std::path::PathBuf>>,
    timings: Timings,
}

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
    /// Ingestion into `replay`, rate limited by `limiter` when given; no
    /// snapshots, no metrics, actors told to explore uniformly throughout.
    pub fn new(replay: Replay, limiter: Option<SharedLimiter>, bounds: ObservationBounds) -> Self {
        Self {
            replay: Mutex::new(replay),
            limiter,
            bounds,
            actors: Mutex::new(HashMap::new()),
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
        }
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
        actors: &BTreeMap<String, u64>,
    ) -> Self {
        self.steps_inserted.store(steps_inserted, Ordering::Relaxed);
        *lock(&self.episodes) = episodes;
        let mut known = lock(&self.actors);
        for (id, &sequence) in actors {
            let source = known.len() as Source;
            known.insert(id.clone(), KnownActor::new(source, Some(sequence)));
        }
        drop(known);
        self
    }

    /// The replay.
    pub fn replay(&self) -> MutexGuard<'_, Replay> {
        lock(&self.replay)
    }

    /// The rate limiter, unless learning is paused.
    pub fn limiter(&self) -> Option<&SharedLimiter> {
        self.limiter.as_ref()
    }

    /// What the rate limiter is doing; `None` while learning is paused.
    pub fn limiter_state(&self) -> Option<LimiterState> {
        self.limiter.as_ref().map(|l| l.snapshot().1)
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
            actors: self.actors(),
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

    /// The bounds every observation of an actor's batch must lie in.
    pub fn bounds(&self) -> &ObservationBounds {
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

    pub(crate) fn stream_opened(&self) {
        self.connected.fetch_add(1, Ordering::Relaxed);
    }

    /// A stream closed; `actor` is the actor it was bound to, if any.
    pub(crate) fn stream_closed(&self, actor: Option<&str>) {
        self.connected.fetch_sub(1, Ordering::Relaxed);
        if let Some(id) = actor
            && let Some(known) = lock(&self.actors).get_mut(id)
        {
            known.streams = known.streams.saturating_sub(1);
        }
    }

    /// Every actor heard from, by id.
    pub fn actors(&self) -> Vec<ActorSummary> {
        let mut actors: Vec<ActorSummary> = lock(&self.actors)
            .iter()
            .map(|(id, known)| ActorSummary {
                id: id.clone(),
                streams: known.streams,
                steps: known.steps,
                episodes: known.episodes,
                idle_seconds: known.last_stored.map(|t| t.elapsed().as_secs_f64()),
                last_sequence: known.last_sequence,
            })
            .collect();
        actors.sort_by(|a, b| a.id.cmp(&b.id));
        actors
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

    /// Asks the trainer for a checkpoint now; the receiver sees it written.
    pub fn request_checkpoint(&self) -> tokio::sync::watch::Receiver<Option<std::path::PathBuf>> {
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
        self.checkpoints.send_replace(Some(path));
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
        let actors = lock(&self.actors)
            .iter()
            .filter_map(|(id, a)| a.last_sequence.map(|s| (id.clone(), s)))
            .collect();
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

    /// Checks and stores one batch of the stream that `stream_actor`
    /// identifies (set by the stream's first batch), waiting for the rate
    /// limiter. A batch stored before (same actor, sequence not above the
    /// last stored) is acknowledged and not stored again. `closed` says the
    /// client went away: a producer waiting on back-pressure then gives up.
    pub fn accept(
        &self,
        batch: ActorBatch,
        stream_actor: &mut Option<String>,
        closed: impl Fn() -> bool,
    ) -> Result<Ack, Refusal> {
        let refuse = |reason: String| {
            self.count_malformed();
            Refusal::Malformed(reason)
        };
        let ActorBatch {
            actor,
            sequence,
            steps,
        } = batch;
        match stream_actor {
            Some(bound) if *bound != actor => {
                return Err(refuse(format!(
                    "actor_id: unknown actor `{actor}` on a stream opened by `{bound}`"
                )));
            }
            Some(_) => {}
            None => {
                *stream_actor = Some(actor.clone());
                let mut actors = lock(&self.actors);
                let next_source = actors.len() as Source;
                actors
                    .entry(actor.clone())
                    .or_insert(KnownActor::new(next_source, None))
                    .streams += 1;
            }
        }
        if let Some((i, reason)) =
            (steps.iter().enumerate()).find_map(|(i, s)| Replay::admits(s).err().map(|e| (i, e)))
        {
            return Err(refuse(format!("steps[{i}]: {reason}")));
        }
        if self.stored_before(&actor, sequence) {
            self.duplicates.fetch_add(1, Ordering::Relaxed);
            return Ok(self.ack(sequence));
        }
        if let Some(limiter) = &self.limiter {
            while !limiter.wait_to_insert(steps.len() as u64, Duration::from_millis(100)) {
                if closed() {
                    return Err(Refusal::Closed);
                }
                if self.stopping() {
                    return Err(Refusal::ShuttingDown);
                }
            }
        }
        let mut finished: Vec<Episode> = Vec::new();
        let len = {
            let mut replay = self.replay();
            let mut actors = lock(&self.actors);
            let next_source = actors.len() as Source;
            let known = actors
                .entry(actor)
                .or_insert(KnownActor::new(next_source, None));
            if known.last_sequence.is_some_and(|last| sequence <= last) {
                // Another stream of the same actor stored it meanwhile.
                self.duplicates.fetch_add(1, Ordering::Relaxed);
                return Ok(self.ack(sequence));
            }
            known.last_sequence = Some(sequence);
            let source = known.source;
            let mut episodes = self.episodes();
            for step in &steps {
                replay
                    .insert(source, step)
                    .expect("steps were checked against the replay's limits");
                finished.extend(episodes.step(source, step));
            }
            known.steps += steps.len() as u64;
            known.episodes += finished.len() as u64;
            known.last_stored = Some(Instant::now());
            drop(actors);
            self.steps_inserted
                .fetch_add(steps.len() as u64, Ordering::Relaxed);
            replay.len()
        };
        if let Some(limiter) = &self.limiter {
            limiter.replay_len(len);
        }
        for episode in finished {
            self.run_log.write("episode", episode);
        }
        Ok(self.ack(sequence))
    }

    fn stored_before(&self, actor: &str, sequence: u64) -> bool {
        lock(&self.actors)
            .get(actor)
            .and_then(|a| a.last_sequence)
            .is_some_and(|last| sequence <= last)
    }
}
