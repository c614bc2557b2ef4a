//! Compact FIFO storage of step records and their sphere centres.

use serde::{Deserialize, Serialize};
use std::collections::{HashMap, VecDeque};
use tweezer_gym::{EndKind, Observation, SplitMix64, StepRecord};

/// Sizes of the replay.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ReplayConfig {
    /// Transitions held before the oldest are removed (SPEC §4: 1,050,000).
    pub capacity: usize,
    /// Sphere centres budgeted per transition; when the centre store is
    /// full the oldest records go first, whatever their number. SPEC density
    /// averages about 12 centres per observation.
    pub centres_per_transition: usize,
}

impl Default for ReplayConfig {
    fn default() -> Self {
        Self {
            capacity: 1_050_000,
            centres_per_transition: 32,
        }
    }
}

/// Which actor a step came from: a small number the learner assigns.
pub type Source = u32;

/// A replay that cannot answer.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum ReplayError {
    /// Nothing to sample yet.
    #[error("the replay holds no complete transition yet")]
    Empty,
    /// An observation lists more centres than a record can index.
    #[error("an observation lists {0} centres, more than the {max} a record holds", max = u16::MAX)]
    TooManyCentres(usize),
}

/// No successor yet.
const NONE: u64 = u64::MAX;

/// One stored observation with, for a step, what followed it.
#[derive(Clone, Copy, Debug)]
struct Record {
    /// Global index of the first centre in the centre store.
    centres_at: u64,
    centres_len: u16,
    /// Set for a step record; a final-observation record has no action.
    step: bool,
    /// The step ended the episode in success or collision (no bootstrap).
    terminated: bool,
    vector: [f32; 2],
    action: [f32; 2],
    reward: f32,
    /// Id of the record with the next observation, or `NONE`.
    next: u64,
}

/// The last step record of an environment that awaits its successor.
#[derive(Clone, Copy, Debug)]
struct Pending {
    id: u64,
    episode: u64,
    t: u32,
}

/// A uniformly sampled batch, laid out for the networks: observations'
/// centres are left to the caller to render.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SampledBatch {
    /// Centres of each observation.
    pub centres: Vec<Vec<[f32; 2]>>,
    /// Target vectors, `[batch, 2]` row-major.
    pub vectors: Vec<f32>,
    /// Actions, `[batch, 2]`.
    pub actions: Vec<f32>,
    /// Rewards, `[batch]`.
    pub rewards: Vec<f32>,
    /// 1 where the step terminated the episode (no bootstrap), else 0.
    pub terminated: Vec<f32>,
    /// Centres of each next observation.
    pub next_centres: Vec<Vec<[f32; 2]>>,
    /// Next target vectors, `[batch, 2]`.
    pub next_vectors: Vec<f32>,
}

/// The replay table.
#[derive(Debug)]
pub struct Replay {
    config: ReplayConfig,
    /// Records in insertion order; the front has id `first_id`.
    records: VecDeque<Record>,
    first_id: u64,
    /// Sphere centres of the records, in the same order; the front has
    /// global index `first_centre`.
    centres: VecDeque<[f32; 2]>,
    first_centre: u64,
    pending: HashMap<(Source, u32), Pending>,
    /// Step records whose successor has arrived.
    transitions: usize,
    inserted: u64,
}

impl Replay {
    /// An empty replay.
    pub fn new(config: ReplayConfig) -> Self {
        Self {
            records: VecDeque::new(),
            first_id: 0,
            centres: VecDeque::new(),
            first_centre: 0,
            pending: HashMap::new(),
            transitions: 0,
            inserted: 0,
            config,
        }
    }

    /// Complete transitions held.
    pub fn len(&self) -> usize {
        self.transitions
    }

    /// Whether no complete transition is held.
    pub fn is_empty(&self) -> bool {
        self.transitions == 0
    }

    /// Transitions held at most.
    pub fn capacity(&self) -> usize {
        self.config.capacity
    }

    /// Transitions completed since the replay was made.
    pub fn inserted(&self) -> u64 {
        self.inserted
    }

    /// Bytes of memory the replay's storage occupies now.
    pub fn bytes(&self) -> usize {
        self.records.capacity() * size_of::<Record>()
            + self.centres.capacity() * size_of::<[f32; 2]>()
            + self.pending.capacity() * (size_of::<(Source, u32)>() + size_of::<Pending>() + 8)
    }

    fn record(&self, id: u64) -> Option<&Record> {
        id.checked_sub(self.first_id)
            .and_then(|i| self.records.get(i as usize))
    }

    fn record_mut(&mut self, id: u64) -> Option<&mut Record> {
        id.checked_sub(self.first_id)
            .and_then(|i| self.records.get_mut(i as usize))
    }

    fn push(&mut self, observation: &Observation, step: Option<(&StepRecord, bool)>) -> u64 {
        let id = self.first_id + self.records.len() as u64;
        let centres_at = self.first_centre + self.centres.len() as u64;
        self.centres.extend(observation.centres.iter().copied());
        let (action, reward, terminated) = match step {
            Some((s, terminated)) => (s.action.components(), s.reward, terminated),
            None => ([0.0; 2], 0.0, false),
        };
        self.records.push_back(Record {
            centres_at,
            centres_len: observation.centres.len() as u16,
            step: step.is_some(),
            terminated,
            vector: observation.vector,
            action,
            reward,
            next: NONE,
        });
        id
    }

    /// Stores one step from `source`, linking it to that environment's
    /// previous step, and removes the oldest records beyond capacity.
    pub fn insert(&mut self, source: Source, step: &StepRecord) -> Result<(), ReplayError> {
        let too_many = |o: &Observation| o.centres.len() > usize::from(u16::MAX);
        if too_many(&step.observation) {
            return Err(ReplayError::TooManyCentres(step.observation.centres.len()));
        }
        if let Some(end) = &step.end
            && too_many(&end.final_observation)
        {
            return Err(ReplayError::TooManyCentres(
                end.final_observation.centres.len(),
            ));
        }
        let terminated = step.terminated();
        let id = self.push(&step.observation, Some((step, terminated)));
        let key = (source, step.env);
        if let Some(previous) = self.pending.remove(&key)
            && previous.episode == step.episode
            && previous.t + 1 == step.t
        {
            self.link(previous.id, id);
        }
        match &step.end {
            None => {
                self.pending.insert(
                    key,
                    Pending {
                        id,
                        episode: step.episode,
                        t: step.t,
                    },
                );
            }
            Some(end) => {
                let last = self.push(&end.final_observation, None);
                self.link(id, last);
                debug_assert_eq!(end.kind == EndKind::Terminated, terminated);
            }
        }
        self.evict();
        Ok(())
    }

    fn link(&mut self, from: u64, to: u64) {
        if let Some(record) = self.record_mut(from) {
            record.next = to;
            self.transitions += 1;
            self.inserted += 1;
        }
    }

    /// Removes the oldest records while the transition count or the centre
    /// budget is exceeded.
    fn evict(&mut self) {
        let centre_budget = self.config.capacity * self.config.centres_per_transition;
        while self.transitions > self.config.capacity || self.centres.len() > centre_budget {
            let Some(oldest) = self.records.pop_front() else {
                break;
            };
            self.first_id += 1;
            if oldest.step && oldest.next != NONE {
                self.transitions -= 1;
            }
            let n = usize::from(oldest.centres_len);
            self.centres.drain(..n);
            self.first_centre += n as u64;
        }
    }

    fn centres_of(&self, record: &Record) -> Vec<[f32; 2]> {
        let start = (record.centres_at - self.first_centre) as usize;
        self.centres
            .range(start..start + usize::from(record.centres_len))
            .copied()
            .collect()
    }

    /// Draws `batch` transitions uniformly at random (with replacement).
    pub fn sample(&self, batch: usize, rng: &mut SplitMix64) -> Result<SampledBatch, ReplayError> {
        if self.transitions == 0 {
            return Err(ReplayError::Empty);
        }
        let mut out = SampledBatch::default();
        for _ in 0..batch {
            let record = self.draw(rng);
            let next = self
                .record(record.next)
                .expect("a record's successor is newer, so still held");
            out.centres.push(self.centres_of(record));
            out.vectors.extend(record.vector);
            out.actions.extend(record.action);
            out.rewards.push(record.reward);
            out.terminated
                .push(if record.terminated { 1.0 } else { 0.0 });
            out.next_centres.push(self.centres_of(next));
            out.next_vectors.extend(next.vector);
        }
        Ok(out)
    }

    /// One complete transition, uniformly: rejection over the records
    /// (most are complete steps), with a scan as the bounded fallback.
    fn draw(&self, rng: &mut SplitMix64) -> &Record {
        let complete = |r: &&Record| r.step && r.next != NONE;
        let n = self.records.len() as u32 - 1;
        for _ in 0..64 {
            let record = &self.records[rng.integer_inclusive(0, n) as usize];
            if complete(&record) {
                return record;
            }
        }
        let k = rng.integer_inclusive(0, self.transitions as u32 - 1) as usize;
        self.records
            .iter()
            .filter(complete)
            .nth(k)
            .expect("k is below the number of complete records")
    }
}
