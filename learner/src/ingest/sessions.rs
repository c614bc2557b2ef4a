//! The actor sessions the learner has heard from, bounded in number: which
//! token owns each, the last batch each stored (so that a resent batch is
//! stored once), and the replay source its steps go to.

use super::batch::Refusal;
use crate::persistence::checkpoint::SessionState;
use crate::replay::Source;
use std::collections::HashMap;
use std::time::{Duration, Instant};

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

/// One actor session, as a status lists it.
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

/// An actor session the learner has heard from.
#[derive(Clone, Debug)]
pub struct Session {
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

impl Session {
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

    /// The replay source its steps are stored under.
    pub fn source(&self) -> Source {
        self.source
    }

    /// Counts a stored batch of `steps` steps that finished `episodes`.
    pub fn stored_batch(&mut self, steps: usize, episodes: usize) {
        self.steps += steps as u64;
        self.episodes += episodes as u64;
        let now = Instant::now();
        self.last_stored = Some(now);
        self.last_seen = now;
    }
}

/// The actor sessions the learner tracks.
#[derive(Debug)]
pub struct Sessions {
    sessions: HashMap<SessionKey, Session>,
    /// The replay source the next new session gets.
    next_source: Source,
    last_sweep: Instant,
}

impl Default for Sessions {
    fn default() -> Self {
        Self {
            sessions: HashMap::new(),
            next_source: 0,
            last_sweep: Instant::now(),
        }
    }
}

impl Sessions {
    /// The sessions a checkpoint saved, up to [`MAX_SESSIONS`], each with
    /// its last stored batch and its replay source.
    pub fn restored(saved: &[SessionState]) -> Self {
        let mut sessions = Self::default();
        for s in saved.iter().take(MAX_SESSIONS) {
            let session = Session::new(s.source, Some(s.sequence), None);
            sessions
                .sessions
                .insert((s.actor.clone(), s.session), session);
            sessions.next_source = sessions.next_source.max(s.source.wrapping_add(1));
        }
        sessions
    }

    /// Sessions tracked now.
    pub fn len(&self) -> usize {
        self.sessions.len()
    }

    /// Whether none is tracked.
    pub fn is_empty(&self) -> bool {
        self.sessions.is_empty()
    }

    /// Binds a new stream to session `key`, made when new, for the caller
    /// holding the token named `token`: a session stays with the token that
    /// opened it, except session 0, which remembers nothing and so any
    /// token may use.
    pub fn open_stream(&mut self, key: &SessionKey, token: Option<&str>) -> Result<(), Refusal> {
        let session = self.entry(key, token)?;
        match (&session.token, token) {
            (Some(owner), Some(caller)) if owner != caller && key.1 != 0 => {
                return Err(Refusal::NotYours(format!(
                    "session {} of actor `{}` was opened with the token `{owner}`, not `{caller}`",
                    key.1, key.0
                )));
            }
            (None, Some(caller)) => session.token = Some(caller.to_string()),
            _ => {}
        }
        session.streams += 1;
        session.last_seen = Instant::now();
        Ok(())
    }

    /// A stream bound to session `key` closed.
    pub fn close_stream(&mut self, key: &SessionKey) {
        if let Some(session) = self.sessions.get_mut(key) {
            session.streams = session.streams.saturating_sub(1);
            session.last_seen = Instant::now();
        }
    }

    /// Whether session `key` stored batch `sequence` before.
    pub fn stored_before(&self, key: &SessionKey, sequence: u64) -> bool {
        (self.sessions.get(key)).is_some_and(|s| s.stored(key.1, sequence))
    }

    /// Session `key`, its last stored batch moved to `sequence`, for the
    /// caller to store the batch under its source; `None` when it stored
    /// that batch already.
    pub fn claim(
        &mut self,
        key: &SessionKey,
        token: Option<&str>,
        sequence: u64,
    ) -> Result<Option<&mut Session>, Refusal> {
        let session = self.entry(key, token)?;
        if session.stored(key.1, sequence) {
            return Ok(None);
        }
        session.last_sequence = Some(sequence);
        Ok(Some(session))
    }

    /// The sessions a status lists: those streaming and the most recently
    /// active first, at most [`STATUS_ACTORS`], by id.
    pub fn summaries(&self) -> Vec<ActorSummary> {
        let mut recent: Vec<(&SessionKey, &Session)> = self.sessions.iter().collect();
        recent.sort_by_key(|(_, s)| (s.streams == 0, std::cmp::Reverse(s.last_seen)));
        let mut actors: Vec<ActorSummary> = recent
            .into_iter()
            .take(STATUS_ACTORS)
            .map(|((id, session), s)| ActorSummary {
                id: id.clone(),
                session: *session,
                token: s.token.clone(),
                streams: s.streams,
                steps: s.steps,
                episodes: s.episodes,
                idle_seconds: s.last_stored.map(|t| t.elapsed().as_secs_f64()),
                last_sequence: s.last_sequence,
            })
            .collect();
        actors.sort_by(|a, b| (&a.id, a.session).cmp(&(&b.id, b.session)));
        actors
    }

    /// What a checkpoint saves: each deduplicated session's last stored
    /// batch and replay source, by id.
    pub fn saved(&self) -> Vec<SessionState> {
        let mut saved: Vec<SessionState> = (self.sessions.iter())
            .filter(|((_, session), _)| *session != 0)
            .filter_map(|((actor, session), s)| {
                s.last_sequence.map(|sequence| SessionState {
                    actor: actor.clone(),
                    session: *session,
                    sequence,
                    source: s.source,
                })
            })
            .collect();
        saved.sort_by(|a, b| (&a.actor, a.session).cmp(&(&b.actor, b.session)));
        saved
    }

    /// The session `key`, made when new (forgetting idle ones to make
    /// room).
    fn entry(&mut self, key: &SessionKey, token: Option<&str>) -> Result<&mut Session, Refusal> {
        if !self.sessions.contains_key(key) {
            if self.last_sweep.elapsed() >= SWEEP_EVERY {
                self.forget_idle();
            }
            if self.sessions.len() >= MAX_SESSIONS {
                self.forget_quietest();
            }
            if self.sessions.len() >= MAX_SESSIONS {
                return Err(Refusal::TooManySessions);
            }
            let source = self.next_source;
            self.next_source = self.next_source.wrapping_add(1);
            let session = Session::new(source, None, token.map(str::to_string));
            self.sessions.insert(key.clone(), session);
        }
        Ok(self.sessions.get_mut(key).expect("inserted above"))
    }

    /// Forgets the tenth of the sessions without an open stream that were
    /// quiet longest (a tenth at once keeps a flood of new ids cheap).
    fn forget_quietest(&mut self) {
        let mut idle: Vec<(Instant, SessionKey)> = (self.sessions.iter())
            .filter(|(_, s)| s.streams == 0)
            .map(|(k, s)| (s.last_seen, k.clone()))
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
            .retain(|_, s| s.streams > 0 || s.last_seen.elapsed() < FORGET_IDLE);
    }
}
