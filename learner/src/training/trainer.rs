//! The training thread: TD3 updates as the rate limiter allows, snapshots
//! every `snapshots.every_updates` updates, metrics lines, and checkpoints
//! periodically and when the learner stops.

use crate::config::LearnerFile;
use crate::ingest::limiter::limiter_state_name;
use crate::persistence::checkpoint::{CheckpointHeader, Checkpoints, Loaded};
use crate::state::LearnerState;
use crate::training::divergence::{DivergenceGuard, Verdict};
use crate::training::minibatch::minibatch_tensors;
use crate::training::mirror::mirror;
use crate::training::td3::{Td3, UpdateStats};
use anyhow::{Context, bail};
use burn::tensor::{Bytes, Device};
use serde::Serialize;
use std::io;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tweezer_gym::SplitMix64;
use tweezer_nets::{
    Architecture, Networks, SnapshotError, SnapshotInfo, encode, encode_with_critics, with_networks,
};

/// Sums of update statistics between two metrics lines.
#[derive(Default)]
struct Sums {
    n: u64,
    critic_loss: f64,
    actor_loss: f64,
    actor_n: u64,
    mean_q: f64,
    update_ms: f64,
}

/// A line of the metrics file about training.
#[derive(Serialize)]
struct UpdateLine {
    updates: u64,
    steps_inserted: u64,
    replay: usize,
    replay_fill: f64,
    critic_loss: f64,
    actor_loss: f64,
    mean_q: f64,
    update_ms: f64,
    insert_rate: f64,
    sample_rate: f64,
    limiter: &'static str,
}

/// Counters at the last rate measurement.
struct RateMark {
    at: Instant,
    steps_inserted: u64,
    updates: u64,
}

/// The training thread's work, whichever networks it trains.
pub trait Training: Send {
    /// Publishes the untrained policy when no snapshot exists yet, so that
    /// a client asking once the learner listens finds one.
    fn publish_first(&mut self) -> anyhow::Result<()>;

    /// Trains until the shared state says stop, then writes a final
    /// checkpoint. An error (a full disk) ends training; a diverged update
    /// does not ([`crate::training::divergence`]).
    fn run(self: Box<Self>) -> anyhow::Result<()>;
}

/// Fresh networks of the architecture `file` configures, or the state of
/// `resumed`, training on `device`.
pub fn training(
    file: &LearnerFile,
    shared: Arc<LearnerState>,
    checkpoints: Checkpoints,
    resumed: Option<&Loaded>,
    device: &Device,
) -> anyhow::Result<Box<dyn Training>> {
    let networks = (file.learner.network.architecture(&file.env)).networks(&file.env)?;
    with_networks!(networks, |networks| {
        let trainer = Trainer::new(networks, file, shared, checkpoints, resumed, device)?;
        Ok(Box::new(trainer))
    })
}

/// The wait before a failed checkpoint is tried again, doubling after
/// each failure up to the last.
const FIRST_CHECKPOINT_RETRY: Duration = Duration::from_secs(5);
const LAST_CHECKPOINT_RETRY: Duration = Duration::from_secs(300);

/// TD3 fed from the shared replay.
struct Trainer<N: Networks> {
    shared: Arc<LearnerState>,
    td3: Td3<N>,
    guard: DivergenceGuard<N>,
    device: Device,
    sampler: SplitMix64,
    file: LearnerFile,
    checkpoints: Checkpoints,
    sums: Sums,
    mark: RateMark,
    last_checkpoint: Instant,
    /// After a failed checkpoint (a full disk): when to try again, and
    /// the wait after the next failure.
    checkpoint_retry: Option<(Instant, Duration)>,
    /// A diverged update could not be rolled back: the networks are not
    /// finite, and no checkpoint or snapshot is written of them.
    poisoned: bool,
}

impl<N: Networks> Training for Trainer<N> {
    fn publish_first(&mut self) -> anyhow::Result<()> {
        let has_snapshot = self
            .shared
            .snapshots()
            .is_some_and(|s| s.latest_version() > 0);
        if !has_snapshot {
            self.publish_or_report();
        }
        Ok(())
    }

    fn run(mut self: Box<Self>) -> anyhow::Result<()> {
        let result = self.train();
        let last = self.checkpoint();
        result.and(last.map(|_| ()))
    }
}

impl<N: Networks> Trainer<N> {
    /// Fresh `networks`, or the state of `resumed`, training on `device`.
    fn new(
        networks: N,
        file: &LearnerFile,
        shared: Arc<LearnerState>,
        checkpoints: Checkpoints,
        resumed: Option<&Loaded>,
        device: &Device,
    ) -> anyhow::Result<Self> {
        let config = &file.learner;
        let device = device.clone().autodiff();
        device.seed(config.seed);
        let architecture = networks.architecture();
        let mut td3 = Td3::new(config.td3.clone(), networks, &device)?;
        let mut sampler = SplitMix64::derived(config.seed, 0x5a3_91e);
        if let Some(loaded) = resumed {
            let header = &loaded.header;
            let trained = header.architecture;
            if trained != architecture {
                bail!(
                    "checkpoint {} holds other networks than the config trains: {}",
                    loaded.path.display(),
                    SnapshotError::mismatch(&architecture, &trained)
                );
            }
            td3.load_state(|name| loaded.part(name), header.updates)
                .with_context(|| format!("checkpoint {}", loaded.path.display()))?;
            sampler = SplitMix64::new(header.sampler_state);
        }
        shared.training().updates = td3.updates();
        Ok(Self {
            mark: RateMark {
                at: Instant::now(),
                steps_inserted: shared.steps_inserted(),
                updates: td3.updates(),
            },
            guard: DivergenceGuard::new(config.rollback, &td3, &checkpoints),
            shared,
            td3,
            device,
            sampler,
            file: file.clone(),
            checkpoints,
            sums: Sums::default(),
            last_checkpoint: Instant::now(),
            checkpoint_retry: None,
            poisoned: false,
        })
    }

    fn train(&mut self) -> anyhow::Result<()> {
        let config = self.file.learner.clone();
        let every_checkpoint = Duration::from_secs_f64(config.checkpoints.every_seconds);
        if self.guard.needs_checkpoint(&self.td3) {
            // Something for a diverged update to roll back to.
            self.checkpoint_or_retry();
        }
        while !self.shared.stopping() {
            if self.shared.take_checkpoint_request() {
                self.checkpoint_or_retry();
            }
            let limit = config.max_updates;
            if self.shared.paused() || (limit > 0 && self.td3.updates() >= limit) {
                std::thread::sleep(Duration::from_millis(20));
                continue;
            }
            let may_update = self
                .shared
                .table()
                .wait_to_update(Duration::from_millis(100));
            if may_update && self.update()? {
                let updates = self.td3.updates();
                if updates.is_multiple_of(config.metrics_every_updates) {
                    self.report();
                }
                if updates.is_multiple_of(config.snapshots.every_updates)
                    || updates == config.max_updates
                {
                    self.publish_or_report();
                }
            } else if self.mark.at.elapsed() >= Duration::from_secs(2) {
                self.measure_rates();
            }
            let due = match self.checkpoint_retry {
                Some((at, _)) => Instant::now() >= at,
                None => {
                    !every_checkpoint.is_zero()
                        && self.last_checkpoint.elapsed() >= every_checkpoint
                }
            };
            if due {
                self.checkpoint_or_retry();
            }
        }
        Ok(())
    }

    /// One update on a uniformly sampled batch; false when it diverged and
    /// was undone.
    fn update(&mut self) -> anyhow::Result<bool> {
        let _span = tracing::debug_span!("update", n = self.td3.updates() + 1).entered();
        let started = Instant::now();
        let learner = &self.file.learner;
        let mut sampled = self.shared.replay().sample_n_step(
            learner.batch_size,
            learner.td3.n_step,
            learner.td3.gamma,
            &mut self.sampler,
        )?;
        if learner.mirror {
            mirror(&mut sampled, self.file.env.fov_px, &mut self.sampler);
        }
        let batch = minibatch_tensors(&sampled, self.td3.networks(), &self.device);
        let stats = self.td3.update(batch);
        self.shared.table().updated();
        let diverged_at = self.td3.updates();
        let verdict = self.guard.check(&mut self.td3, &stats);
        if verdict != Verdict::Finite {
            self.diverged(diverged_at, &stats, verdict);
            return Ok(false);
        }
        let s = &mut self.sums;
        s.n += 1;
        s.critic_loss += stats.critic_loss;
        s.mean_q += stats.mean_q;
        let seconds = started.elapsed().as_secs_f64();
        s.update_ms += seconds * 1e3;
        self.shared.timings().update_seconds.observe(seconds);
        if let Some(a) = stats.actor_loss {
            s.actor_loss += a;
            s.actor_n += 1;
        }
        self.shared.training().updates = self.td3.updates();
        Ok(true)
    }

    /// Reports an update that diverged (the networks are rolled back
    /// already), and pauses learning when rolling back did not help or
    /// could not be done.
    fn diverged(&mut self, at: u64, stats: &UpdateStats, verdict: Verdict) {
        {
            let mut training = self.shared.training();
            training.updates = self.td3.updates();
            training.diverged_updates += 1;
        }
        let (lost, paused) = match &verdict {
            Verdict::Finite => return,
            Verdict::RolledBack { lost } => (Some(*lost), false),
            Verdict::GiveUp { lost } => (Some(*lost), true),
            Verdict::Unrestorable { .. } => (None, true),
        };
        if let Verdict::Unrestorable { reason } = &verdict {
            self.poisoned = true;
            tracing::error!(
                update = at,
                critic_loss = stats.critic_loss,
                mean_q = stats.mean_q,
                %reason,
                "an update diverged and no good state could be read back: learning is paused, and no checkpoint is written of these networks; restart the learner from a good checkpoint"
            );
        } else {
            tracing::warn!(
                update = at,
                critic_loss = stats.critic_loss,
                mean_q = stats.mean_q,
                rolled_back_to = self.td3.updates(),
                lost,
                "an update diverged: the networks are rolled back and the batch dropped"
            );
        }
        if let Verdict::GiveUp { .. } = verdict {
            tracing::error!(
                rollbacks = crate::training::divergence::MAX_ROLLBACKS,
                updates = self.td3.updates(),
                "training keeps diverging after rollbacks: learning is paused with the last good networks; check the TD3 settings (learning rates, reward_scale), then ResumeLearning"
            );
        }
        if paused {
            self.shared.set_paused(true);
        }
        #[derive(Serialize)]
        struct DivergenceLine {
            update: u64,
            critic_loss: f64,
            mean_q: f64,
            rolled_back_to: Option<u64>,
            paused: bool,
        }
        self.shared.run_log().write(
            "divergence",
            DivergenceLine {
                update: at,
                critic_loss: stats.critic_loss,
                mean_q: stats.mean_q,
                rolled_back_to: lost.map(|_| self.td3.updates()),
                paused,
            },
        );
    }

    /// Insert and sample rates since the last measurement, into status.
    fn measure_rates(&mut self) -> (f64, f64) {
        let now = Instant::now();
        let seconds = now.duration_since(self.mark.at).as_secs_f64().max(1e-9);
        let (inserted, updates) = (self.shared.steps_inserted(), self.td3.updates());
        let insert_rate = (inserted - self.mark.steps_inserted) as f64 / seconds;
        let sample_rate =
            ((updates - self.mark.updates) * self.file.learner.batch_size as u64) as f64 / seconds;
        self.mark = RateMark {
            at: now,
            steps_inserted: inserted,
            updates,
        };
        let mut training = self.shared.training();
        training.insert_rate = insert_rate;
        training.sample_rate = sample_rate;
        (insert_rate, sample_rate)
    }

    /// Means since the last report, into status and the metrics file.
    fn report(&mut self) {
        let (insert_rate, sample_rate) = self.measure_rates();
        let s = std::mem::take(&mut self.sums);
        let n = s.n.max(1) as f64;
        let (replay, capacity) = {
            let replay = self.shared.replay();
            (replay.len(), replay.capacity())
        };
        let line = UpdateLine {
            updates: self.td3.updates(),
            steps_inserted: self.shared.steps_inserted(),
            replay,
            replay_fill: replay as f64 / capacity.max(1) as f64,
            critic_loss: s.critic_loss / n,
            actor_loss: s.actor_loss / s.actor_n.max(1) as f64,
            mean_q: s.mean_q / n,
            update_ms: s.update_ms / n,
            insert_rate,
            sample_rate,
            limiter: limiter_state_name(self.shared.limiter_state()),
        };
        {
            let mut training = self.shared.training();
            training.critic_loss = line.critic_loss;
            training.actor_loss = line.actor_loss;
            training.mean_q = line.mean_q;
        }
        tracing::info!(
            updates = line.updates,
            steps = line.steps_inserted,
            critic_loss = line.critic_loss,
            mean_q = line.mean_q,
            update_ms = line.update_ms,
            "training"
        );
        self.shared.run_log().write("update", line);
    }

    /// Publishes the current policy; a failure (a full disk) is reported
    /// and training goes on: the next publication tries again.
    fn publish_or_report(&mut self) {
        if let Err(e) = self.publish() {
            self.shared.training().snapshot_failures += 1;
            tracing::error!(error = %format!("{e:#}"), "no snapshot published; training goes on and the next one is tried as usual");
        }
    }

    /// Writes a checkpoint; a failure (a full disk) is reported (log,
    /// metric, and to a Checkpoint call waiting for it) and training goes
    /// on, trying again after a wait that doubles from
    /// [`FIRST_CHECKPOINT_RETRY`] up to [`LAST_CHECKPOINT_RETRY`]. The
    /// last good checkpoint stays: a failed write leaves it untouched.
    fn checkpoint_or_retry(&mut self) {
        match self.checkpoint() {
            Ok(_) => self.checkpoint_retry = None,
            Err(e) => {
                let reason = format!("{e:#}");
                let wait = self
                    .checkpoint_retry
                    .map_or(FIRST_CHECKPOINT_RETRY, |(_, wait)| {
                        (wait * 2).min(LAST_CHECKPOINT_RETRY)
                    });
                self.checkpoint_retry = Some((Instant::now() + wait, wait));
                self.shared.training().checkpoint_failures += 1;
                tracing::error!(error = %reason, retry_in = ?wait, "checkpoint failed; training goes on, and the last good checkpoint is kept");
                self.shared.checkpoint_failed(reason);
            }
        }
    }

    /// Publishes the current policy as the next snapshot version, a set
    /// network's with the critics that check it.
    fn publish(&mut self) -> anyhow::Result<()> {
        let _span = tracing::info_span!("publish").entered();
        let rolling = self.shared.episodes().rolling();
        let rolling_return = (rolling.episodes > 0).then_some(rolling.mean_return);
        let Some(mut snapshots) = self.shared.snapshots() else {
            return Ok(());
        };
        let info = SnapshotInfo {
            architecture: self.td3.networks().architecture(),
            version: snapshots.next_version(),
            training_step: self.td3.updates(),
        };
        // The set network's critics are small and cheap to ask; the CNN's
        // are as large as its actor and would render 64 images a step.
        let bytes = match info.architecture {
            Architecture::Set(_) => encode_with_critics(
                &self.td3.policy(),
                &self.td3.critics(),
                self.td3.reward_scale(),
                &info,
            ),
            Architecture::Paper { .. } => encode(&self.td3.policy(), &info),
        };
        let (published, best) = snapshots.publish(bytes, rolling_return)?;
        drop(snapshots);
        tracing::info!(
            version = published.info.version,
            updates = info.training_step,
            rolling_return,
            best,
            "snapshot published"
        );
        #[derive(Serialize)]
        struct SnapshotLine {
            version: u64,
            updates: u64,
            rolling_return: Option<f64>,
            rolling_success_rate: f64,
            episodes: usize,
            best: bool,
        }
        self.shared.run_log().write(
            "snapshot",
            SnapshotLine {
                version: published.info.version,
                updates: info.training_step,
                rolling_return,
                rolling_success_rate: rolling.success_rate,
                episodes: rolling.episodes,
                best,
            },
        );
        Ok(())
    }

    /// Writes a checkpoint of everything training needs to go on, unless
    /// the networks are poisoned.
    fn checkpoint(&mut self) -> anyhow::Result<Option<PathBuf>> {
        let _span = tracing::info_span!("checkpoint").entered();
        if self.poisoned {
            tracing::warn!("no checkpoint written: the networks diverged and were not restored");
            return Ok(None);
        }
        let started = Instant::now();
        let captured = self.shared.capture(self.file.learner.checkpoints.replay);
        let header = CheckpointHeader {
            updates: self.td3.updates(),
            steps_inserted: captured.steps_inserted,
            sampler_state: self.sampler.state(),
            architecture: self.td3.networks().architecture(),
            episodes: captured.episodes,
            snapshots: self
                .shared
                .snapshots()
                .map(|s| s.state())
                .unwrap_or_default(),
            sessions: captured.actors,
            parts: Vec::new(),
        };
        let replay = captured
            .replay
            .map(|replay| Ok(("replay", Bytes::from_bytes_vec(replay))));
        let parts = self
            .td3
            .state_parts()
            .map(|part| part.map_err(io::Error::other));
        let path = self.checkpoints.write(header, parts.chain(replay))?;
        // The snapshots the kept checkpoints need stay on disk until no
        // kept checkpoint needs them. Their headers are read before the
        // store is locked: every acknowledgement takes that lock.
        let needed = self.checkpoints.needed_snapshots();
        if let Some(mut snapshots) = self.shared.snapshots() {
            snapshots.pin(needed);
        }
        self.last_checkpoint = Instant::now();
        self.shared.checkpoint_written(path.clone());
        let seconds = started.elapsed().as_secs_f64();
        tracing::info!(path = %path.display(), seconds, "checkpoint written");
        #[derive(Serialize)]
        struct CheckpointLine<'a> {
            path: &'a std::path::Path,
            updates: u64,
            seconds: f64,
        }
        self.shared.run_log().write(
            "checkpoint",
            CheckpointLine {
                path: &path,
                updates: self.td3.updates(),
                seconds,
            },
        );
        Ok(Some(path))
    }
}
