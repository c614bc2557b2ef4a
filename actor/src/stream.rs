//! `actor run`: steps vectorised environments with the learner's current policy
//! and streams the steps to it.
//!
//! Actions are uniformly random while the learner's acknowledgements say so
//! (`docs/spec.md` §4's first 10,000 steps), then the newest snapshot's actions
//! plus Gaussian noise ([`ExplorationNoise`]). At most `max_unacked` batches
//! are in flight: when the learner applies back-pressure the actor waits
//! instead of queueing. When the
//! learner goes away the actor reconnects with exponential backoff and jitter
//! and resends the batches it has no acknowledgement for; the learner
//! recognises a resent batch by its session (a random number drawn at start)
//! and sequence number, and stores it once.

use crate::exploration::ExplorationNoise;
use anyhow::Context;
use burn::tensor::Device;
use serde::Serialize;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::runtime::Runtime;
use tweezer_actor::config::ActorFile;
use tweezer_gym::{Action, Outcome, Planner, Policy, SplitMix64, UniformRandom, VecEnv};
use tweezer_nets::NetworkPolicy;
use tweezer_process::StopSignals;
use tweezer_proto::pb::learner_client::LearnerClient;
use tweezer_proto::pb::snapshot_request::Selector;
use tweezer_proto::{download_snapshot, pb, step_to_wire};
use tweezer_rpc::{AuthChannel, ClientSecurity, Histogram, ServerSecurity, latency_buckets};

/// What a run did, printed as JSON when it ends.
#[derive(Clone, Debug, Default, Serialize)]
pub struct RunReport {
    /// Steps the learner acknowledged.
    pub steps_acked: u64,
    /// Batches sent, resends included.
    pub batches_sent: u64,
    /// Connections made after the first.
    pub reconnects: u64,
    /// Episodes finished.
    pub episodes: u64,
    /// Mean return of the finished episodes.
    pub mean_return: f64,
    /// Fraction of finished episodes that reached the target.
    pub success_rate: f64,
    /// Snapshot versions loaded, in order.
    pub snapshots_loaded: Vec<u64>,
    /// Batches sent but not acknowledged when the actor stopped (not
    /// counted in `steps_acked`).
    pub batches_unacknowledged: u64,
}

/// An open `StreamSteps` call.
struct Link {
    /// When the learner last answered: the stream opened, or an ack came.
    heard: Instant,
    client: LearnerClient<AuthChannel>,
    batches: tokio::sync::mpsc::Sender<pb::StepBatch>,
    acks: mpsc::Receiver<Result<pb::StepAck, tonic::Status>>,
    /// The largest batch the learner decodes, in bytes.
    max_message_bytes: usize,
}

/// The longest the actor waits on the learner, for an acknowledgement or
/// a snapshot, before it takes the link for broken and reconnects (resent
/// batches are stored once). Keepalive pings find a connection that died
/// silently within 20 s; this bounds a learner that is reachable but no
/// longer answers, and is well above the limiter's longest wait on a slow
/// learner.
const LINK_DEADLINE: Duration = Duration::from_secs(300);

/// Room kept in a message for the batch's own fields (id, session,
/// sequence) and protobuf framing.
const BATCH_OVERHEAD: usize = 1024;

/// Splits `steps` into runs whose encoded batches fit in `max_bytes`, in
/// order; an error when a single step does not fit.
fn split_to_fit(steps: Vec<pb::Step>, max_bytes: usize) -> anyhow::Result<Vec<Vec<pb::Step>>> {
    use prost::Message;
    let budget = max_bytes.saturating_sub(BATCH_OVERHEAD);
    let mut runs = vec![Vec::new()];
    let mut used = 0;
    for step in steps {
        let len = step.encoded_len();
        let size = 1 + prost::encoding::encoded_len_varint(len as u64) + len;
        if size > budget {
            anyhow::bail!(
                "one step encodes to {size} bytes, more than the {max_bytes} bytes the learner takes in a message: raise the learner's max_message_bytes"
            );
        }
        if used + size > budget {
            runs.push(Vec::new());
            used = 0;
        }
        used += size;
        runs.last_mut().expect("never empty").push(step);
    }
    Ok(runs)
}

/// Exponential backoff with ±50 % jitter.
struct Backoff {
    initial: Duration,
    max: Duration,
    next: Duration,
    rng: SplitMix64,
}

impl Backoff {
    fn wait(&mut self) -> Duration {
        let jittered = self.next.mul_f64(0.5 + self.rng.unit());
        self.next = (self.next * 2).min(self.max);
        jittered
    }

    fn reset(&mut self) {
        self.next = self.initial;
    }
}

/// The actor's state across connections.
struct Actor {
    file: ActorFile,
    security: ClientSecurity,
    /// The report as of the last batch, for the metrics endpoint.
    published: Arc<Mutex<RunReport>>,
    /// Seconds to step the environments for one batch.
    batch_seconds: Histogram,
    runtime: Runtime,
    envs: VecEnv,
    actions: Vec<Action>,
    uniform: UniformRandom,
    noise: ExplorationNoise,
    /// Drives the first `actor.demonstrators` environments.
    planner: Planner,
    policy: Option<(u64, NetworkPolicy)>,
    explore_uniformly: bool,
    newest_snapshot: u64,
    unacked: VecDeque<pb::StepBatch>,
    session: u64,
    next_sequence: u64,
    steps_sent: u64,
    returns: f64,
    successes: u64,
    report: RunReport,
}

/// How long a stopping actor waits for its batches in flight to be
/// acknowledged: a learner applying back-pressure may hold them for long.
const STOP_DRAIN: Duration = Duration::from_secs(3);

/// This process's session: a random number, so that the learner tells its
/// batches from those of any other process under the same id (an earlier
/// run, or another client) and recognises resent ones by their sequence.
fn new_session() -> anyhow::Result<u64> {
    loop {
        let session = getrandom::u64().map_err(|e| anyhow::anyhow!("no random session: {e}"))?;
        if session != 0 {
            return Ok(session);
        }
    }
}

/// Streams until `stop` is set or `steps` steps have been acknowledged,
/// connecting as `security` says, with Prometheus metrics served as
/// `metrics` says (when `actor.metrics_listen` is set); returns what was
/// done.
pub fn run(
    file: ActorFile,
    security: ClientSecurity,
    metrics: Option<ServerSecurity>,
    steps: Option<u64>,
    stop: Arc<AtomicBool>,
) -> anyhow::Result<RunReport> {
    let config = file.actor.clone();
    let seed = config.effective_seed();
    tracing::info!(id = %config.id, seed, "actor starting");
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    stop_on_signal(&runtime, stop.clone())?;
    let mut actor = Actor::new(file, security, seed, runtime)?;
    if let (Some(listen), Some(metrics)) = (config.metrics_listen, metrics) {
        actor.serve_metrics(listen, metrics)?;
    }
    actor.stream(steps, &stop)?;
    Ok(actor.summary())
}

/// Sets `stop` on SIGINT or SIGTERM.
fn stop_on_signal(runtime: &Runtime, stop: Arc<AtomicBool>) -> std::io::Result<()> {
    let mut signals = StopSignals::install(runtime.handle())?;
    runtime.spawn(async move {
        let signal = signals.recv().await;
        tracing::info!(
            signal,
            "stopping once the batches in flight are acknowledged (at most 3 s)"
        );
        stop.store(true, Ordering::Relaxed);
    });
    Ok(())
}

/// Why a step of the loop failed.
enum Broken {
    /// The connection: reconnect.
    Link(String),
    /// Something reconnecting cannot mend.
    Fatal(anyhow::Error),
}

impl Actor {
    /// An actor of `file`'s environments and settings, seeded by `seed`,
    /// in a new session, not yet connected.
    fn new(
        file: ActorFile,
        security: ClientSecurity,
        seed: u64,
        runtime: Runtime,
    ) -> anyhow::Result<Self> {
        let config = &file.actor;
        Ok(Self {
            envs: VecEnv::new(&file.env, config.envs, seed)?,
            actions: vec![Action::ZERO; config.envs],
            uniform: UniformRandom::new(seed),
            noise: ExplorationNoise::new(
                config.noise,
                config.noise_correlation,
                config.envs,
                SplitMix64::derived(seed, 0x0015e),
            ),
            planner: Planner::for_config(&file.env),
            policy: None,
            explore_uniformly: true,
            newest_snapshot: 0,
            unacked: VecDeque::new(),
            session: new_session()?,
            next_sequence: 0,
            steps_sent: 0,
            returns: 0.0,
            successes: 0,
            report: RunReport::default(),
            runtime,
            file,
            security,
            published: Arc::new(Mutex::new(RunReport::default())),
            batch_seconds: Histogram::new(latency_buckets()),
        })
    }

    /// Acts and streams batches until `steps` steps are acknowledged or
    /// `stop` is set (then the batches in flight get [`STOP_DRAIN`] to be
    /// acknowledged), reconnecting with backoff whenever the link breaks.
    fn stream(&mut self, steps: Option<u64>, stop: &AtomicBool) -> anyhow::Result<()> {
        let config = self.file.actor.clone();
        let mut backoff = Backoff {
            initial: Duration::from_millis(config.reconnect_initial_ms),
            max: Duration::from_millis(config.reconnect_max_ms),
            next: Duration::from_millis(config.reconnect_initial_ms),
            rng: SplitMix64::derived(config.effective_seed(), 0xbac0ff),
        };
        let mut link: Option<Link> = None;
        let mut connections = 0u64;
        let mut last_log = Instant::now();
        let mut stopping_since: Option<Instant> = None;
        while steps.is_none_or(|n| self.report.steps_acked < n) {
            let stopping = stop.load(Ordering::Relaxed);
            if stopping && self.drained(*stopping_since.get_or_insert_with(Instant::now)) {
                break;
            }
            let Some(open) = link.as_mut() else {
                if stopping {
                    break;
                }
                match self.connect() {
                    Ok(l) => {
                        connections += 1;
                        self.report.reconnects = connections - 1;
                        backoff.reset();
                        link = Some(l);
                    }
                    Err(e) => {
                        let wait = backoff.wait();
                        tracing::warn!(error = %format!("{e:#}"), ?wait, "cannot reach the learner; retrying");
                        std::thread::sleep(wait);
                    }
                }
                continue;
            };
            let sending = !stopping && steps.is_none_or(|n| self.steps_sent < n);
            let result = if sending && self.unacked.len() < config.max_unacked {
                self.send_next(open)
            } else {
                self.await_ack(open, Duration::from_millis(200))
            };
            match result {
                Ok(()) => {}
                Err(Broken::Link(e)) => {
                    tracing::warn!(error = %e, "lost the learner; reconnecting");
                    link = None;
                }
                Err(Broken::Fatal(e)) => return Err(e),
            }
            if last_log.elapsed() >= Duration::from_secs(10) {
                last_log = Instant::now();
                self.log_progress();
            }
        }
        Ok(())
    }

    /// Whether an actor stopping since `since` may stop now: every batch
    /// acknowledged, or [`STOP_DRAIN`] spent waiting.
    fn drained(&self, since: Instant) -> bool {
        if self.unacked.is_empty() {
            return true;
        }
        if since.elapsed() < STOP_DRAIN {
            return false;
        }
        tracing::warn!(
            batches = self.unacked.len(),
            "stopping with batches unacknowledged (the learner holds them back)"
        );
        true
    }

    /// Logs the acknowledged steps, episodes and returns so far.
    fn log_progress(&self) {
        let r = self.summary();
        tracing::info!(
            steps = r.steps_acked,
            episodes = r.episodes,
            mean_return = r.mean_return,
            success_rate = r.success_rate,
            snapshot = self.policy.as_ref().map_or(0, |p| p.0),
            "acting"
        );
    }
    /// Serves the actor's metrics at `listen` until the process ends.
    fn serve_metrics(
        &self,
        listen: std::net::SocketAddr,
        security: ServerSecurity,
    ) -> anyhow::Result<()> {
        let listener = self
            .runtime
            .block_on(tokio::net::TcpListener::bind(listen))
            .with_context(|| format!("cannot listen on {listen} (actor.metrics_listen)"))?;
        let addr = listener.local_addr()?;
        tracing::info!(metrics_addr = %addr, "Prometheus metrics at /metrics");
        let registry = Arc::new(crate::prometheus_metrics::prometheus(
            self.published.clone(),
            &self.batch_seconds,
        ));
        self.runtime.spawn(async move {
            security
                .serve_metrics(listener, registry, std::future::pending())
                .await;
        });
        Ok(())
    }

    fn summary(&self) -> RunReport {
        let mut report = self.report.clone();
        let n = report.episodes.max(1) as f64;
        report.mean_return = self.returns / n;
        report.success_rate = self.successes as f64 / n;
        report.batches_unacknowledged = self.unacked.len() as u64;
        report
    }

    /// Connects, opens a stream and resends what is unacknowledged.
    fn connect(&mut self) -> anyhow::Result<Link> {
        let address = self.file.actor.learner.clone();
        let security = self.security.clone();
        let (batches, receiver) = tokio::sync::mpsc::channel(self.file.actor.max_unacked + 1);
        let (ack_tx, acks) = mpsc::channel();
        let client = self.runtime.block_on(async move {
            let channel = security
                .connect(&address, Duration::from_secs(5))
                .await
                .context("cannot connect to the learner")?;
            let mut client = LearnerClient::new(channel);
            let response = client
                .stream_steps(tokio_stream::wrappers::ReceiverStream::new(receiver))
                .await?;
            // A learner that does not say takes gRPC's default.
            let max_message_bytes = response
                .metadata()
                .get(tweezer_proto::MAX_MESSAGE_HEADER)
                .and_then(|v| v.to_str().ok()?.parse().ok())
                .unwrap_or(tweezer_proto::DEFAULT_MAX_MESSAGE_BYTES);
            let mut stream = response.into_inner();
            tokio::spawn(async move {
                loop {
                    let next = match stream.message().await {
                        Ok(Some(ack)) => Ok(ack),
                        Ok(None) => Err(tonic::Status::unavailable("the learner ended the stream")),
                        Err(status) => Err(status),
                    };
                    let end = next.is_err();
                    if ack_tx.send(next).is_err() || end {
                        break;
                    }
                }
            });
            anyhow::Ok((client, max_message_bytes))
        })?;
        let (client, max_message_bytes) = client;
        tracing::debug!(max_message_bytes, "stream open");
        for batch in &self.unacked {
            batches
                .blocking_send(batch.clone())
                .context("the stream closed while resending")?;
            self.report.batches_sent += 1;
        }
        Ok(Link {
            heard: Instant::now(),
            client,
            batches,
            acks,
            max_message_bytes,
        })
    }

    /// Steps the environments for one batch and sends it.
    fn send_next(&mut self, link: &mut Link) -> Result<(), Broken> {
        self.take_acks(link)?;
        let batch_steps = self.file.actor.batch_steps;
        let started = Instant::now();
        let mut steps = Vec::with_capacity(batch_steps);
        while steps.len() < batch_steps {
            self.act();
            self.envs
                .step(&self.actions)
                .map_err(|e| Broken::Fatal(e.into()))?;
            for (i, slot) in self.envs.slots().iter().enumerate() {
                if let Some(record) = slot.record(i as u32) {
                    steps.push(step_to_wire(&record));
                }
                if let Some(episode) = slot.finished() {
                    self.report.episodes += 1;
                    self.returns += episode.episode_return;
                    self.successes += u64::from(episode.outcome == Outcome::Success);
                }
            }
        }
        let runs = split_to_fit(steps, link.max_message_bytes).map_err(Broken::Fatal)?;
        for steps in runs {
            let batch = pb::StepBatch {
                actor_id: self.file.actor.id.clone(),
                session: self.session,
                sequence: self.next_sequence,
                steps,
            };
            self.next_sequence += 1;
            self.steps_sent += batch.steps.len() as u64;
            self.unacked.push_back(batch.clone());
            self.report.batches_sent += 1;
            link.batches
                .blocking_send(batch)
                .map_err(|_| Broken::Link("the stream closed".into()))?;
        }
        self.batch_seconds.observe(started.elapsed().as_secs_f64());
        *self.published.lock().unwrap_or_else(|p| p.into_inner()) = self.summary();
        Ok(())
    }

    /// Chooses every environment's action: the planner's for the
    /// demonstrators, the policy's (or uniform ones while the learner asks
    /// for them) for the rest; noise on all but uniform ones.
    fn act(&mut self) {
        let observations = self.envs.observations();
        let demonstrators = self.file.actor.demonstrators;
        let (shown, own) = self.actions.split_at_mut(demonstrators);
        self.planner.act(&observations[..demonstrators], shown);
        let noisy = match (&mut self.policy, self.explore_uniformly) {
            (Some((_, policy)), false) => {
                policy.act(&observations[demonstrators..], own);
                self.actions.len()
            }
            _ => {
                for a in own {
                    *a = self.uniform.sample();
                }
                demonstrators
            }
        };
        for (env, a) in self.actions[..noisy].iter_mut().enumerate() {
            let [x, y] = a.components();
            let [nx, ny] = self.noise.next(env);
            *a = Action::clipped(x + nx as f32, y + ny as f32).unwrap_or(Action::ZERO);
        }
    }

    /// Handles acknowledgements already received.
    fn take_acks(&mut self, link: &mut Link) -> Result<(), Broken> {
        loop {
            match link.acks.try_recv() {
                Ok(ack) => self.acknowledged(link, ack)?,
                Err(mpsc::TryRecvError::Empty) => return Ok(()),
                Err(mpsc::TryRecvError::Disconnected) => {
                    return Err(Broken::Link("the stream closed".into()));
                }
            }
        }
    }

    /// Waits up to `timeout` for an acknowledgement; the link is broken
    /// when batches have waited [`LINK_DEADLINE`] for one.
    fn await_ack(&mut self, link: &mut Link, timeout: Duration) -> Result<(), Broken> {
        match link.acks.recv_timeout(timeout) {
            Ok(ack) => self.acknowledged(link, ack)?,
            Err(mpsc::RecvTimeoutError::Timeout) => {
                if !self.unacked.is_empty() && link.heard.elapsed() > LINK_DEADLINE {
                    return Err(Broken::Link(format!(
                        "no acknowledgement for {LINK_DEADLINE:?}: the learner is unreachable or stalled"
                    )));
                }
            }
            Err(mpsc::RecvTimeoutError::Disconnected) => {
                return Err(Broken::Link("the stream closed".into()));
            }
        }
        self.take_acks(link)
    }

    fn acknowledged(
        &mut self,
        link: &mut Link,
        ack: Result<pb::StepAck, tonic::Status>,
    ) -> Result<(), Broken> {
        link.heard = Instant::now();
        let ack = match ack {
            Ok(ack) => ack,
            // Refusals that sending again cannot mend (RESOURCE_EXHAUSTED:
            // a batch over the learner's message limit).
            Err(status)
                if matches!(
                    status.code(),
                    tonic::Code::InvalidArgument
                        | tonic::Code::PermissionDenied
                        | tonic::Code::OutOfRange
                        | tonic::Code::ResourceExhausted
                ) =>
            {
                return Err(Broken::Fatal(anyhow::anyhow!(
                    "the learner refused a batch ({:?}): {}",
                    status.code(),
                    status.message()
                )));
            }
            Err(status) => {
                return Err(Broken::Link(format!(
                    "{}: {}",
                    status.code(),
                    status.message()
                )));
            }
        };
        while self
            .unacked
            .front()
            .is_some_and(|b| b.sequence <= ack.sequence)
        {
            let batch = self.unacked.pop_front().expect("front exists");
            self.report.steps_acked += batch.steps.len() as u64;
        }
        self.explore_uniformly = ack.explore_uniformly;
        self.newest_snapshot = self.newest_snapshot.max(ack.snapshot_version);
        let loaded = self.policy.as_ref().map_or(0, |p| p.0);
        if !self.explore_uniformly && self.newest_snapshot > loaded {
            self.load_snapshot(link)?;
        }
        Ok(())
    }

    /// Fetches and loads the learner's newest snapshot.
    fn load_snapshot(&mut self, link: &mut Link) -> Result<(), Broken> {
        let client = &mut link.client;
        let download = download_snapshot(client, Selector::Tag(pb::SnapshotTag::Latest.into()));
        let downloaded = self
            .runtime
            .block_on(async { tokio::time::timeout(LINK_DEADLINE, download).await })
            .map_err(|_| {
                Broken::Link(format!(
                    "no snapshot within {LINK_DEADLINE:?}: the learner is unreachable or stalled"
                ))
            })?;
        let (info, bytes) = match downloaded {
            Ok(d) => d,
            Err(tweezer_proto::DownloadError::Status(s)) if s.code() == tonic::Code::NotFound => {
                return Ok(());
            }
            Err(e) => return Err(Broken::Link(e.to_string())),
        };
        let (policy, _) = NetworkPolicy::from_snapshot(&bytes, &self.file.env, &Device::flex())
            .map_err(|e| {
                Broken::Fatal(anyhow::anyhow!(
                    "snapshot version {} from the learner cannot be used: {e}",
                    info.version
                ))
            })?;
        tracing::info!(version = info.version, "loaded the learner's snapshot");
        self.report.snapshots_loaded.push(info.version);
        // TD3 explores around its actor's action: the critics' check is for
        // evaluation and the instrument.
        self.policy = Some((info.version, policy.actor_alone()));
        Ok(())
    }
}
