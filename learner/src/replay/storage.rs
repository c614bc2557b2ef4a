//! Compact FIFO storage of step records and their sphere centres, each with
//! its displacement since the previous step, and of a guide's action for
//! each step's observation where one was labelled.

use serde::{Deserialize, Serialize};
use std::collections::{HashMap, VecDeque};
use tweezer_gym::{Observation, SplitMix64, StepRecord};

/// Sizes of the replay.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ReplayConfig {
    /// Transitions held before the oldest are removed (`docs/spec.md` §4:
    /// 1,050,000).
    pub capacity: usize,
    /// Sphere centres budgeted per transition; when the centre store is full
    /// the oldest records go first, whatever their number. The spec's density
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

/// Steps awaiting a successor held before the first sweep, and records
/// allowed beyond twice the capacity.
const MIN_PENDING_SWEEP: usize = 4096;

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
    /// The guide's action for this observation; NaN where none was given.
    guide: [f32; 2],
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
pub struct SampledTransitions {
    /// Centres of each observation.
    pub centres: Vec<Vec<[f32; 2]>>,
    /// Their displacements (`None`: new to the view), one per centre.
    pub displacements: Vec<Vec<Option<[f32; 2]>>>,
    /// Target vectors, `[batch, 2]` row-major.
    pub vectors: Vec<f32>,
    /// Actions, `[batch, 2]`.
    pub actions: Vec<f32>,
    /// Rewards, `[batch]`: with n-step returns, the discounted sum over
    /// the steps taken.
    pub rewards: Vec<f32>,
    /// 1 where a step taken terminated the episode (no bootstrap), else 0.
    pub terminated: Vec<f32>,
    /// Steps taken from each observation to its next, `[batch]`: 1, or up
    /// to n with n-step returns (fewer where the episode ended first).
    pub steps: Vec<f32>,
    /// Centres of each next observation.
    pub next_centres: Vec<Vec<[f32; 2]>>,
    /// Their displacements.
    pub next_displacements: Vec<Vec<Option<[f32; 2]>>>,
    /// Next target vectors, `[batch, 2]`.
    pub next_vectors: Vec<f32>,
    /// The guide's action for each observation, `[batch, 2]`; NaN where
    /// none was given.
    pub guides: Vec<f32>,
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
    /// Each centre's displacement, NaN for none, in step with `centres`.
    displacements: VecDeque<[f32; 2]>,
    first_centre: u64,
    pending: HashMap<(Source, u32), Pending>,
    /// Size of `pending` at which entries whose record is gone are swept.
    sweep_pending_at: usize,
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
            displacements: VecDeque::new(),
            first_centre: 0,
            pending: HashMap::new(),
            sweep_pending_at: MIN_PENDING_SWEEP,
            transitions: 0,
            inserted: 0,
            config,
        }
    }

    /// Most records held: a transition's step record and, at worst, one
    /// final observation each, plus steps awaiting their successor. Steps
    /// that never get one (a client whose `t` never advances) count too,
    /// so memory stays bounded by the capacity whatever clients send.
    fn record_limit(&self) -> usize {
        2 * self.config.capacity + MIN_PENDING_SWEEP
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
            + (self.centres.capacity() + self.displacements.capacity()) * size_of::<[f32; 2]>()
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

    fn push(
        &mut self,
        observation: &Observation,
        step: Option<(&StepRecord, bool)>,
        guide: Option<[f32; 2]>,
    ) -> u64 {
        let id = self.first_id + self.records.len() as u64;
        let centres_at = self.first_centre + self.centres.len() as u64;
        self.centres.extend(observation.centres.iter().copied());
        self.displacements.extend(
            (0..observation.centres.len())
                .map(|k| observation.displacement(k).unwrap_or([f32::NAN; 2])),
        );
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
            guide: guide.unwrap_or([f32::NAN; 2]),
            next: NONE,
        });
        id
    }

    /// Whether a record can hold `step`: every observation lists at most
    /// 65,535 centres.
    pub fn admits(step: &StepRecord) -> Result<(), ReplayError> {
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
        Ok(())
    }

    /// Stores one step from `source`, linking it to that environment's
    /// previous step, and removes the oldest records beyond capacity.
    pub fn insert(&mut self, source: Source, step: &StepRecord) -> Result<(), ReplayError> {
        self.insert_guided(source, step, None)
    }

    /// [`Self::insert`], with the guide's action for the step's observation.
    pub fn insert_guided(
        &mut self,
        source: Source,
        step: &StepRecord,
        guide: Option<[f32; 2]>,
    ) -> Result<(), ReplayError> {
        Self::admits(step)?;
        let terminated = step.terminated();
        let id = self.push(&step.observation, Some((step, terminated)), guide);
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
                let last = self.push(&end.final_observation, None, None);
                self.link(id, last);
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

    /// Removes the oldest records while the transition count, the record
    /// limit or the centre budget is exceeded, and forgets steps awaiting a
    /// successor whose record is gone.
    fn evict(&mut self) {
        let centre_budget = self.config.capacity * self.config.centres_per_transition;
        let record_limit = self.record_limit();
        while self.transitions > self.config.capacity
            || self.records.len() > record_limit
            || self.centres.len() > centre_budget
        {
            let Some(oldest) = self.records.pop_front() else {
                break;
            };
            self.first_id += 1;
            if oldest.step && oldest.next != NONE {
                self.transitions -= 1;
            }
            let n = usize::from(oldest.centres_len);
            self.centres.drain(..n);
            self.displacements.drain(..n);
            self.first_centre += n as u64;
        }
        // Each live entry names a distinct held record, so after a sweep at
        // most `record_limit` remain: sweeping at twice what remained keeps
        // the cost amortised.
        if self.pending.len() > self.sweep_pending_at {
            let first_id = self.first_id;
            self.pending.retain(|_, p| p.id >= first_id);
            self.sweep_pending_at = (2 * self.pending.len()).max(MIN_PENDING_SWEEP);
        }
    }

    fn centres_of(&self, record: &Record) -> Vec<[f32; 2]> {
        self.centres
            .range(self.spheres_of(record))
            .copied()
            .collect()
    }

    fn displacements_of(&self, record: &Record) -> Vec<Option<[f32; 2]>> {
        self.displacements
            .range(self.spheres_of(record))
            .map(|d| (!d[0].is_nan()).then_some(*d))
            .collect()
    }

    /// Where a record's centres and displacements lie in their stores.
    fn spheres_of(&self, record: &Record) -> std::ops::Range<usize> {
        let start = (record.centres_at - self.first_centre) as usize;
        start..start + usize::from(record.centres_len)
    }

    /// Draws `batch` transitions uniformly at random (with replacement).
    pub fn sample(
        &self,
        batch: usize,
        rng: &mut SplitMix64,
    ) -> Result<SampledTransitions, ReplayError> {
        self.sample_n_step(batch, 1, 1.0, rng)
    }

    /// Draws `batch` transitions uniformly at random (with replacement),
    /// each followed up to `n` steps along its episode: the rewards summed
    /// with discount `gamma`, the next observation the last reached. A
    /// step that ends the episode, or whose successor has not arrived,
    /// ends the walk early.
    pub fn sample_n_step(
        &self,
        batch: usize,
        n: u32,
        gamma: f64,
        rng: &mut SplitMix64,
    ) -> Result<SampledTransitions, ReplayError> {
        if self.transitions == 0 {
            return Err(ReplayError::Empty);
        }
        let successor = |r: &Record| {
            self.record(r.next)
                .expect("a record's successor is newer, so still held")
        };
        let mut out = SampledTransitions::default();
        for _ in 0..batch {
            let record = self.draw(rng);
            let (mut last, mut next) = (record, successor(record));
            let (mut reward, mut steps, mut discount) = (f64::from(record.reward), 1, 1.0);
            while steps < n && !last.terminated && next.step && next.next != NONE {
                discount *= gamma;
                reward += discount * f64::from(next.reward);
                steps += 1;
                (last, next) = (next, successor(next));
            }
            out.centres.push(self.centres_of(record));
            out.displacements.push(self.displacements_of(record));
            out.vectors.extend(record.vector);
            out.actions.extend(record.action);
            out.rewards.push(reward as f32);
            out.terminated.push(if last.terminated { 1.0 } else { 0.0 });
            out.steps.push(steps as f32);
            out.next_centres.push(self.centres_of(next));
            out.next_displacements.push(self.displacements_of(next));
            out.next_vectors.extend(next.vector);
            out.guides.extend(record.guide);
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

/// A replay file that cannot be read back.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("replay state is corrupt: {0}")]
pub struct ReplayDecodeError(String);

/// Little-endian reads from a byte slice, failing cleanly at its end.
struct Reader<'a>(&'a [u8]);

impl Reader<'_> {
    fn take<const N: usize>(&mut self) -> Result<[u8; N], ReplayDecodeError> {
        if self.0.len() < N {
            return Err(ReplayDecodeError("truncated".into()));
        }
        let (head, rest) = self.0.split_at(N);
        self.0 = rest;
        Ok(head.try_into().expect("split at N"))
    }
    fn u64(&mut self) -> Result<u64, ReplayDecodeError> {
        self.take().map(u64::from_le_bytes)
    }
    fn u32(&mut self) -> Result<u32, ReplayDecodeError> {
        self.take().map(u32::from_le_bytes)
    }
    fn f32(&mut self) -> Result<f32, ReplayDecodeError> {
        self.take().map(f32::from_le_bytes)
    }
    fn count(&mut self, item_bytes: usize) -> Result<usize, ReplayDecodeError> {
        let n = self.u64()? as usize;
        if n.saturating_mul(item_bytes) > self.0.len() {
            return Err(ReplayDecodeError(format!("{n} items do not fit the data")));
        }
        Ok(n)
    }
}

const RECORD_BYTES: usize = 8 + 2 + 1 + 5 * 4 + 8;

impl Replay {
    /// The replay's contents as bytes (little-endian), for a checkpoint:
    /// the counters, records, centres and pending steps, then the centres'
    /// displacements (NaN for none), which replays from before motion was
    /// observed lack, then the records' guide actions (NaN for none), which
    /// replays from before guides lack.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(
            72 + self.records.len() * RECORD_BYTES
                + self.centres.len() * 16
                + self.pending.len() * 24,
        );
        for v in [
            self.first_id,
            self.first_centre,
            self.transitions as u64,
            self.inserted,
            self.records.len() as u64,
        ] {
            out.extend(v.to_le_bytes());
        }
        for r in &self.records {
            out.extend(r.centres_at.to_le_bytes());
            out.extend(r.centres_len.to_le_bytes());
            out.push(u8::from(r.step) | u8::from(r.terminated) << 1);
            for v in [r.vector[0], r.vector[1], r.action[0], r.action[1], r.reward] {
                out.extend(v.to_le_bytes());
            }
            out.extend(r.next.to_le_bytes());
        }
        out.extend((self.centres.len() as u64).to_le_bytes());
        for c in &self.centres {
            out.extend(c[0].to_le_bytes());
            out.extend(c[1].to_le_bytes());
        }
        out.extend((self.pending.len() as u64).to_le_bytes());
        for (&(source, env), p) in &self.pending {
            out.extend(source.to_le_bytes());
            out.extend(env.to_le_bytes());
            out.extend(p.id.to_le_bytes());
            out.extend(p.episode.to_le_bytes());
            out.extend(p.t.to_le_bytes());
        }
        out.extend((self.displacements.len() as u64).to_le_bytes());
        for d in &self.displacements {
            out.extend(d[0].to_le_bytes());
            out.extend(d[1].to_le_bytes());
        }
        out.extend((self.records.len() as u64).to_le_bytes());
        for r in &self.records {
            out.extend(r.guide[0].to_le_bytes());
            out.extend(r.guide[1].to_le_bytes());
        }
        out
    }

    /// A replay with `config` holding what [`Self::encode`] wrote. The
    /// contents are checked for consistency; a smaller capacity than the
    /// saved one drops the oldest records.
    pub fn decode(config: ReplayConfig, bytes: &[u8]) -> Result<Self, ReplayDecodeError> {
        let corrupt = |what: &str| ReplayDecodeError(what.into());
        let mut r = Reader(bytes);
        let mut replay = Replay::new(config);
        replay.first_id = r.u64()?;
        replay.first_centre = r.u64()?;
        let transitions = r.u64()? as usize;
        replay.inserted = r.u64()?;
        let n = r.count(RECORD_BYTES)?;
        replay.records.reserve_exact(n);
        for _ in 0..n {
            let centres_at = r.u64()?;
            let centres_len = u16::from_le_bytes(r.take()?);
            let [flags] = r.take()?;
            let mut f = [0.0; 5];
            for v in &mut f {
                *v = r.f32()?;
            }
            replay.records.push_back(Record {
                centres_at,
                centres_len,
                step: flags & 1 != 0,
                terminated: flags & 2 != 0,
                vector: [f[0], f[1]],
                action: [f[2], f[3]],
                reward: f[4],
                guide: [f32::NAN; 2],
                next: r.u64()?,
            });
        }
        let n = r.count(8)?;
        replay.centres.reserve_exact(n);
        for _ in 0..n {
            replay.centres.push_back([r.f32()?, r.f32()?]);
        }
        let n = r.count(28)?;
        for _ in 0..n {
            let key = (r.u32()?, r.u32()?);
            let pending = Pending {
                id: r.u64()?,
                episode: r.u64()?,
                t: r.u32()?,
            };
            replay.pending.insert(key, pending);
        }
        if r.0.is_empty() {
            // A replay from before motion was observed: every sphere new.
            replay.displacements = vec![[f32::NAN; 2]; replay.centres.len()].into();
        } else {
            let n = r.count(8)?;
            if n != replay.centres.len() {
                return Err(corrupt("the displacements do not match the centres"));
            }
            replay.displacements.reserve_exact(n);
            for _ in 0..n {
                replay.displacements.push_back([r.f32()?, r.f32()?]);
            }
        }
        // Replays from before guides have none.
        if !r.0.is_empty() {
            let n = r.count(8)?;
            if n != replay.records.len() {
                return Err(corrupt("the guides do not match the records"));
            }
            for record in &mut replay.records {
                record.guide = [r.f32()?, r.f32()?];
            }
        }
        if !r.0.is_empty() {
            return Err(corrupt("trailing bytes"));
        }
        let end_id = replay.first_id + replay.records.len() as u64;
        let end_centre = replay.first_centre + replay.centres.len() as u64;
        let mut complete = 0;
        for record in &replay.records {
            let centres_end = record.centres_at + u64::from(record.centres_len);
            if record.centres_at < replay.first_centre || centres_end > end_centre {
                return Err(corrupt("a record's centres lie outside the centre store"));
            }
            if record.next != NONE {
                if record.next >= end_id || record.next < replay.first_id {
                    return Err(corrupt("a record links outside the replay"));
                }
                complete += usize::from(record.step);
            }
        }
        if complete != transitions {
            return Err(corrupt("the transition count does not match the records"));
        }
        replay.transitions = transitions;
        replay.evict();
        Ok(replay)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tweezer_gym::{EnvConfig, RandomSteps};

    fn filled(config: &ReplayConfig, guided: bool) -> Replay {
        let mut replay = Replay::new(config.clone());
        for (k, record) in RandomSteps::new(&EnvConfig::default(), 4, 3)
            .unwrap()
            .take(300)
            .enumerate()
        {
            let guide = guided.then_some([k as f32 / 300.0, -0.5]);
            replay.insert_guided(1, &record, guide).unwrap();
        }
        replay
    }

    /// Bytes of the guide section [`Replay::encode`] writes last.
    fn guide_section(replay: &Replay) -> usize {
        8 + 8 * replay.records.len()
    }

    #[test]
    fn a_replay_saved_before_motion_was_observed_reads_every_sphere_as_new() {
        let config = ReplayConfig {
            capacity: 200,
            ..ReplayConfig::default()
        };
        let replay = filled(&config, false);
        assert!(replay.displacements.iter().any(|d| !d[0].is_nan()));
        let bytes = replay.encode();
        let old = &bytes[..bytes.len() - guide_section(&replay) - 8 - 8 * replay.centres.len()];
        let back = Replay::decode(config.clone(), old).unwrap();
        assert_eq!(back.centres, replay.centres);
        assert_eq!(back.displacements.len(), replay.centres.len());
        assert!(back.displacements.iter().all(|d| d[0].is_nan()));
        // A displacement section that does not match the centres is refused.
        let mut short = old.to_vec();
        short.extend(1u64.to_le_bytes());
        short.extend([0; 8]);
        assert!(Replay::decode(config, &short).is_err());
    }

    #[test]
    fn n_step_draws_sum_rewards_along_the_episode_and_stop_at_its_end() {
        let config = ReplayConfig {
            capacity: 1000,
            ..ReplayConfig::default()
        };
        let mut replay = Replay::new(config);
        let env = EnvConfig {
            time_limit: 10,
            ..EnvConfig::default()
        };
        let records: Vec<StepRecord> = RandomSteps::new(&env, 1, 5).unwrap().take(400).collect();
        for record in &records {
            replay.insert(1, record).unwrap();
        }
        let sampled = replay
            .sample_n_step(300, 3, 0.5, &mut SplitMix64::new(3))
            .unwrap();
        let mut ended_early = 0;
        for i in 0..300 {
            let a = &sampled.actions[2 * i..2 * i + 2];
            let k = (records.iter())
                .position(|r| r.action.components() == [a[0], a[1]])
                .unwrap();
            if k + 3 >= records.len() {
                continue; // the walk may meet a step still awaiting its successor
            }
            let (mut reward, mut steps, mut discount, mut terminated) = (0.0, 0, 1.0, false);
            for r in &records[k..] {
                reward += discount * f64::from(r.reward);
                (steps, discount, terminated) = (steps + 1, discount * 0.5, r.terminated());
                if steps == 3 || r.end.is_some() {
                    break;
                }
            }
            assert_eq!(sampled.steps[i], steps as f32, "draw {i}");
            assert!(
                (f64::from(sampled.rewards[i]) - reward).abs() < 1e-3,
                "draw {i}"
            );
            assert_eq!(sampled.terminated[i], f32::from(u8::from(terminated)));
            ended_early += usize::from(steps < 3);
        }
        assert!(ended_early > 0, "some draws meet an episode's end");
    }

    #[test]
    fn guides_are_sampled_with_their_step_and_survive_a_checkpoint() {
        let config = ReplayConfig {
            capacity: 200,
            ..ReplayConfig::default()
        };
        let replay = filled(&config, true);
        let sampled = replay.sample(64, &mut SplitMix64::new(7)).unwrap();
        assert_eq!(sampled.guides.len(), 128);
        assert!(sampled.guides.chunks(2).all(|g| g[1] == -0.5 && g[0] > 0.0));
        let bytes = replay.encode();
        let back = Replay::decode(config.clone(), &bytes).unwrap();
        let guides = |r: &Replay| {
            (r.records.iter())
                .map(|r| r.guide.map(f32::to_bits))
                .collect::<Vec<_>>()
        };
        assert_eq!(guides(&back), guides(&replay));
        // A replay saved before guides has none; a section that does not
        // match the records is refused.
        let old = &bytes[..bytes.len() - guide_section(&replay)];
        let back = Replay::decode(config.clone(), old).unwrap();
        assert!(back.records.iter().all(|r| r.guide[0].is_nan()));
        let mut short = old.to_vec();
        short.extend(1u64.to_le_bytes());
        short.extend([0; 8]);
        assert!(Replay::decode(config, &short).is_err());
    }
}
