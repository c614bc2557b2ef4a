//! What the gRPC service and the training thread share: the replay, the
//! rate limiter, the actors known by their ids, episode statistics, the
//! published snapshots and the training status. Actors' batches enter here,
//! decoded by the service: each is checked whole before any step touches the
//! replay.

use crate::checkpoint::SessionState;
use crate::episodes::{Episode, Episodes, Rolling};
use crate::limiter::{Limiter, LimiterState};
use crate::replay::{Replay, Source};
use crate::run_log::RunLog;
use crate::snapshots::Snapshots;
use crate::table::{ReplayGuard, Table};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tweezer_gym::{Planner, StepBounds, StepRecord};
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
    /// Updates that diverged and were rolled back since this process
    /// started.
    pub diverged_updates: u64,
    /// Checkpoints that could not be written since this process started.
    pub checkpoint_failures: u64,
    /// Snapshots that could not be published since this process started.
    pub snapshot_failures: u64,
}

/// One batch of an actor's steps, decoded at the service edge.
#[derive(Clone, Debug, PartialEq)]
pub struct ActorBatch {
    /// The actor's id.
    pub actor: String,
    /// The actor process's session: a random number it keeps across
    /// reconnects. Resent batches are recognised within a session; 0: the
    /// actor asks for no deduplication.
    pub session: u64,
    /// Its sequence number among the session's batches.
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
    /// The session was opened with another token.
    #[error("{0}")]
    NotYours(String),
    /// The learner tracks as many actor sessions as it may, all of them
    /// streaming.
    #[error(
        "the learner tracks {MAX_SESSIONS} actor sessions, all with open streams; try again later"
    )]
    TooManySessions,
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
    /// The actor sessions tracked now, streaming ones and the most
    /// recently active first, at most [`STATUS_ACTORS`], by id.
    pub actors: Vec<ActorSummary>,
    /// Actor sessions tracked now.
    pub known_actors: usize,
}

/// Most actor sessions the learner tracks; past this, the tenth quiet
/// longest without an open stream is forgotten.
pub const MAX_SESSIONS: usize = 10_000;

/// A session without an open stream is forgotten after this long idle.
pub const FORGET_IDLE: Duration = Duration::from_secs(3600);

/// Most actor sessions a status lists.
pub const STATUS_ACTORS: usize = 100;

/// How often idle sessions are looked for while new ones arrive.
const SWEEP_EVERY: Duration = Duration::from_secs(10);

/// An actor session: its id and the random number it drew at start.
pub type SessionKey = (String, u64);

/// An actor session the learner has heard from.
#[derive(Clone, Debug)]
struct KnownActor {
    source: Source,
    /// The last batch stored.
    last_sequence: Option<u64>,
    /// The name of the token that opened it (None: no tokens in use, or
    /// restored from a checkpoint).
    token: Option<String>,
    /// Open streams bound to it.
    streams: u32,
    /// Steps stored and episodes finished since this process started.
    steps: u64,
    episodes: u64,
    /// When its last batch was stored.
    last_stored: Option<Instant>,
    /// When a stream last opened or closed, or a batch was stored.
    last_seen: Instant,
}

impl KnownActor {
    fn new(source: Source, last_sequence: Option<u64>, token: Option<String>) -> Self {
        Self {
            source,
            last_sequence,
            token,
            streams: 0,
            steps: 0,
            episodes: 0,
            last_stored: None,
            last_seen: Instant::now(),
        }
    }

    /// Whether batch `sequence` of this session (numbered `session`) was
    /// stored before; never in session 0, which asks for no deduplication.
    fn stored(&self, session: u64, sequence: u64) -> bool {
        session != 0 && self.last_sequence.is_some_and(|last| sequence <= last)
    }
}

/// The actor sessions the learner tracks, bounded in number.
#[derive(Debug)]
struct Registry {
    sessions: HashMap<SessionKey, KnownActor>,
    /// The replay source the next new session gets.
    next_source: Source,
    last_sweep: Instant,
}

impl Registry {
    fn new() -> Self {
        Self {
            sessions: HashMap::new(),
            next_source: 0,
            last_sweep: Instant::now(),
        }
    }

    /// The session `key`, made when new (forgetting idle ones to make
    /// room); `None` when every tracked session streams.
    fn entry(&mut self, key: &SessionKey, token: Option<&str>) -> Option<&mut KnownActor> {
        if !self.sessions.contains_key(key) {
            if self.last_sweep.elapsed() >= SWEEP_EVERY {
                self.forget_idle();
            }
            if self.sessions.len() >= MAX_SESSIONS {
                self.forget_quietest();
            }
            if self.sessions.len() >= MAX_SESSIONS {
                return None;
            }
            let source = self.next_source;
            self.next_source = self.next_source.wrapping_add(1);
            self.sessions.insert(
                key.clone(),
                KnownActor::new(source, None, token.map(str::to_string)),
            );
        }
        self.sessions.get_mut(key)
    }

    /// Forgets the tenth of the sessions without an open stream that were
    /// quiet longest (a tenth at once keeps a flood of new ids cheap).
    fn forget_quietest(&mut self) {
        let mut idle: Vec<(Instant, SessionKey)> = self
            .sessions
            .iter()
            .filter(|(_, a)| a.streams == 0)
            .map(|(k, a)| (a.last_seen, k.clone()))
            .collect();
        let n = (MAX_SESSIONS / 10).min(idle.len());
        if n == 0 {
            return;
        }
        idle.select_nth_unstable_by_key(n - 1, |(seen, _)| *seen);
        for (_, key) in &idle[..n] {
            self.sessions.remove(key);
        }
    }

    /// Forgets sessions idle for [`FORGET_IDLE`] without an open stream.
    fn forget_idle(&mut self) {
        self.last_sweep = Instant::now();
        self.sessions
            .retain(|_, a| a.streams > 0 || a.last_seen.elapsed() < FORGET_IDLE);
    }
}

/// One actor session, as the learner sees it.
#[derive(Clone, Debug, PartialEq)]
pub struct ActorSummary {
    /// Its id.
    pub id: String,
    /// Its session (0: not deduplicated).
    pub session: u64,
    /// The name of the token that opened the session, if known.
    pub token: Option<String>,
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
    /// Each session's last stored batch and replay source.
    pub actors: Vec<SessionState>,
}

/// The learner's shared state.
#[derive(Debug)]
pub struct LearnerState {
    table: Table,
    bounds: StepBounds,
    actors: Mutex<Registry>,
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
            actors: Mutex::new(Registry::new()),
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
        let mut registry = lock(&self.actors);
        for a in actors.iter().take(MAX_SESSIONS) {
            let known = KnownActor::new(a.source, Some(a.sequence), None);
            registry
                .sessions
                .insert((a.actor.clone(), a.session), known);
            registry.next_source = registry.next_source.max(a.source.wrapping_add(1));
        }
        drop(registry);
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
        let known_actors = lock(&self.actors).sessions.len();
        let actors = self.actors();
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
        if let Some(key) = session
            && let Some(known) = lock(&self.actors).sessions.get_mut(key)
        {
            known.streams = known.streams.saturating_sub(1);
            known.last_seen = Instant::now();
        }
    }

    /// The sessions a status lists: those streaming and the most recently
    /// active first, at most [`STATUS_ACTORS`], by id.
    pub fn actors(&self) -> Vec<ActorSummary> {
        let registry = lock(&self.actors);
        let mut recent: Vec<(&SessionKey, &KnownActor)> = registry.sessions.iter().collect();
        recent.sort_by_key(|(_, a)| (a.streams == 0, std::cmp::Reverse(a.last_seen)));
        let mut actors: Vec<ActorSummary> = recent
            .into_iter()
            .take(STATUS_ACTORS)
            .map(|((id, session), known)| ActorSummary {
                id: id.clone(),
                session: *session,
                token: known.token.clone(),
                streams: known.streams,
                steps: known.steps,
                episodes: known.episodes,
                idle_seconds: known.last_stored.map(|t| t.elapsed().as_secs_f64()),
                last_sequence: known.last_sequence,
            })
            .collect();
        actors.sort_by(|a, b| (&a.id, a.session).cmp(&(&b.id, b.session)));
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
        let mut actors: Vec<SessionState> = lock(&self.actors)
            .sessions
            .iter()
            .filter(|((_, session), _)| *session != 0)
            .filter_map(|((actor, session), a)| {
                a.last_sequence.map(|sequence| SessionState {
                    actor: actor.clone(),
                    session: *session,
                    sequence,
                    source: a.source,
                })
            })
            .collect();
        actors.sort_by(|a, b| (&a.actor, a.session).cmp(&(&b.actor, b.session)));
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
                let mut registry = lock(&self.actors);
                let known = registry
                    .entry(&key, token)
                    .ok_or(Refusal::TooManySessions)?;
                // Session 0 asks for nothing to be remembered: any token
                // may use it.
                match (&known.token, token) {
                    (Some(owner), Some(caller)) if owner != caller && key.1 != 0 => {
                        return Err(Refusal::NotYours(format!(
                            "session {} of actor `{}` was opened with the token `{owner}`, not `{caller}`",
                            key.1, key.0
                        )));
                    }
                    (None, Some(caller)) => known.token = Some(caller.to_string()),
                    _ => {}
                }
                known.streams += 1;
                known.last_seen = Instant::now();
                drop(registry);
                *stream_session = Some(key.clone());
            }
        }
        if let Some((i, reason)) =
            (steps.iter().enumerate()).find_map(|(i, s)| Replay::admits(s).err().map(|e| (i, e)))
        {
            return Err(refuse(format!("steps[{i}]: {reason}")));
        }
        if self.stored_before(&key, sequence) {
            self.duplicates.fetch_add(1, Ordering::Relaxed);
            return Ok(self.ack(sequence));
        }
        // Labelled before the table is held: the planner takes about 0.1 ms
        // an observation.
        let guides: Vec<Option<[f32; 2]>> = match &self.guide {
            Some(planner) => {
                let mut planner = planner.clone();
                (steps.iter())
                    .map(|s| Some(planner.action(&s.observation).components()))
                    .collect()
            }
            None => vec![None; steps.len()],
        };
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
        let mut registry = lock(&self.actors);
        let known = registry.entry(key, token).ok_or(Refusal::TooManySessions)?;
        if known.stored(key.1, sequence) {
            return Ok(None);
        }
        known.last_sequence = Some(sequence);
        let source = known.source;
        let mut episodes = self.episodes();
        let mut finished = Vec::new();
        for (step, guide) in steps.iter().zip(guides) {
            replay
                .insert_guided(source, step, guide)
                .expect("steps were checked against the replay's limits");
            finished.extend(episodes.step(source, step));
        }
        known.steps += steps.len() as u64;
        known.episodes += finished.len() as u64;
        let now = Instant::now();
        known.last_stored = Some(now);
        known.last_seen = now;
        self.steps_inserted
            .fetch_add(steps.len() as u64, Ordering::Relaxed);
        Ok(Some(finished))
    }

    fn stored_before(&self, key: &SessionKey, sequence: u64) -> bool {
        lock(&self.actors)
            .sessions
            .get(key)
            .is_some_and(|a| a.stored(key.1, sequence))
    }
}
