//! `learner serve` as a real process, fed over real gRPC: it learns, serves
//! snapshots in chunks, checkpoints on SIGTERM, resumes, and skips a
//! checkpoint cut short.

use std::path::{Path, PathBuf};
use std::time::Duration;
use tweezer_gym::{
    Action, EnvConfig, EvalSummary, Observation, Policy, SplitMix64, UniformRandom, VecEnv,
    evaluate,
};
use tweezer_nets::NetworkPolicy;
use tweezer_proto::pb::learner_client::LearnerClient;
use tweezer_proto::pb::snapshot_request::Selector;
use tweezer_proto::{download_snapshot, pb, step_to_wire};
use tweezer_rpc::AuthChannel;
use tweezer_system_tests::{
    Running, connect, credentials, learner_status, start_service_with_env, stderr_of_failure,
};

/// No free spheres, 20 x 16 images, the carry and time rewards only (so
/// that Q is about direction alone): learnable in a few thousand updates.
/// Rewards scaled by 0.1 and an action penalty: without them the critics
/// fit these rewards slowly and the actor's tanh saturates in one corner
/// first (measured; see docs/training.md, Training notes).
const TINY: &str = r#"
[env]
min_free_spheres = 0
max_free_spheres = 0
time_limit = 200
[env.rewards]
off = ["success", "collision"]
[env.image]
width = 20
height = 16

[learner]
listen = "127.0.0.1:0"
uniform_steps = 2000
metrics_every_updates = 100
[learner.td3]
reward_scale = 0.1
action_l2 = 1.0
[learner.replay]
capacity = 50000
[learner.limiter]
min_size = 500
[learner.snapshots]
every_updates = 500
keep = 2
[learner.checkpoints]
every_seconds = 0
keep = 3
replay = true
"#;

fn tiny_env() -> EnvConfig {
    let file: toml::Table = toml::from_str(TINY).unwrap();
    file["env"].clone().try_into().unwrap()
}

/// A learner process serving with the test deployment's credentials, its
/// log in a file; killed if the test ends without stopping it.
struct Learner {
    process: Running,
    addr: String,
    log: PathBuf,
    /// The environment its actors step.
    env: EnvConfig,
}

impl Learner {
    /// `learner serve` with `args`, logging into `dir`.
    fn start(dir: &Path, args: &[&str]) -> Self {
        Self::start_with_env(dir, args, &[])
    }

    /// [`Learner::start`] with `vars` added to its environment.
    fn start_with_env(dir: &Path, args: &[&str], vars: &[(&str, &str)]) -> Self {
        let log = (0..)
            .map(|n| dir.join(format!("learner-{n}.log")))
            .find(|path| !path.exists())
            .expect("a free log name");
        let security = credentials().file("server");
        let mut all = vec!["serve", "--security", &security];
        all.extend_from_slice(args);
        let (child, addr) = start_service_with_env("learner", &all, vars, Some(&log));
        Self {
            process: Running::new(child),
            addr,
            log,
            env: tiny_env(),
        }
    }

    /// A new run in `run` with the config file `config`.
    fn fresh(dir: &Path, config: &Path, run: &Path) -> Self {
        let mut learner = Self::start(dir, &run_args(config, run));
        let file: toml::Table = toml::from_str(&std::fs::read_to_string(config).unwrap()).unwrap();
        learner.env = file["env"].clone().try_into().unwrap();
        learner
    }

    /// A client with the actors' token (which may also read).
    async fn client(&self) -> LearnerClient<AuthChannel> {
        LearnerClient::new(connect(&self.addr, "actor").await)
    }

    async fn status(&self) -> pb::LearnerStatus {
        learner_status(&self.addr, "read").await.unwrap()
    }

    /// SIGTERM, then the exit status and everything it logged.
    fn stop(self) -> (std::process::ExitStatus, String) {
        let (status, _) = self.process.stop();
        (status, std::fs::read_to_string(&self.log).unwrap())
    }
}

/// `learner serve` arguments for the config file `config` and the run
/// directory `run`.
fn run_args<'a>(config: &'a Path, run: &'a Path) -> [&'a str; 4] {
    [
        "--config",
        config.to_str().unwrap(),
        "--run-dir",
        run.to_str().unwrap(),
    ]
}

/// A temporary directory with the tiny config file and a run directory.
fn run_dir() -> (tempfile::TempDir, PathBuf, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("learner.toml");
    std::fs::write(&config, TINY).unwrap();
    let run = dir.path().join("run");
    (dir, run, config)
}

/// The session [`Feeder`]s' batches belong to.
const SESSION: u64 = 0x5e55_1011;

/// An actor of 8 environments on one stream of steps to a learner: actions
/// uniformly random while the learner says so, then, as a real actor's,
/// those of the learner's latest snapshot plus Gaussian noise.
struct Feeder {
    client: LearnerClient<AuthChannel>,
    actor: String,
    envs: VecEnv,
    rng: SplitMix64,
    tx: tokio::sync::mpsc::Sender<pb::StepBatch>,
    acks: tonic::Streaming<pb::StepAck>,
    /// The sequence number of the next batch.
    sequence: u64,
    /// Whether the last batch sent awaits its acknowledgement.
    pending: bool,
    uniform: bool,
    /// The latest snapshot downloaded: its version, bytes and policy.
    snapshot: Option<(u64, Vec<u8>, NetworkPolicy)>,
}

impl Feeder {
    /// Opens the stream as actor `actor`.
    async fn start(learner: &Learner, actor: &str) -> Self {
        let mut client = learner.client().await;
        let (tx, rx) = tokio::sync::mpsc::channel(2);
        let acks = client
            .stream_steps(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await
            .unwrap()
            .into_inner();
        Self {
            client,
            actor: actor.into(),
            envs: VecEnv::new(&learner.env, 8, 11).unwrap(),
            rng: SplitMix64::new(5),
            tx,
            acks,
            sequence: 0,
            pending: false,
            uniform: true,
            snapshot: None,
        }
    }

    /// The version of the latest snapshot downloaded (0: none yet).
    fn version(&self) -> u64 {
        self.snapshot.as_ref().map_or(0, |(version, ..)| *version)
    }

    /// Streams steps until the learner's status satisfies `done`, checked
    /// after every acknowledgement and every second while one is held
    /// back, each newer snapshot downloaded first; returns that status. A
    /// batch still unacknowledged then is awaited by the next call.
    async fn until(
        &mut self,
        learner: &Learner,
        done: impl Fn(&pb::LearnerStatus) -> bool,
    ) -> pb::LearnerStatus {
        loop {
            if !self.pending {
                self.send().await;
                self.pending = true;
            }
            let ack = loop {
                let wait = tokio::time::timeout(Duration::from_secs(1), self.acks.message());
                if let Ok(ack) = wait.await {
                    break ack.unwrap().unwrap();
                }
                let status = self.refreshed(learner).await;
                if done(&status) {
                    return status;
                }
            };
            assert_eq!(ack.sequence, self.sequence);
            self.sequence += 1;
            self.pending = false;
            self.uniform = ack.explore_uniformly;
            let status = self.refreshed(learner).await;
            if done(&status) {
                return status;
            }
        }
    }

    /// One batch of 64 steps or more.
    async fn send(&mut self) {
        let mut actions = vec![Action::ZERO; self.envs.len()];
        let mut steps = Vec::new();
        while steps.len() < 64 {
            match &mut self.snapshot {
                Some((.., policy)) if !self.uniform => {
                    policy.act(&self.envs.observations(), &mut actions)
                }
                _ => actions.fill(Action::ZERO),
            }
            for a in &mut actions {
                let [x, y] = if self.uniform {
                    [0.0, 0.0].map(|_: f32| 2.0 * self.rng.unit() as f32 - 1.0)
                } else {
                    let [x, y] = a.components();
                    let noise = [0.0, 0.0].map(|_: f32| 0.2 * self.rng.normal() as f32);
                    [x + noise[0], y + noise[1]]
                };
                *a = Action::clipped(x, y).unwrap();
            }
            self.envs.step(&actions).unwrap();
            steps.extend(
                self.envs
                    .slots()
                    .iter()
                    .enumerate()
                    .filter_map(|(i, s)| s.record(i as u32))
                    .map(|r| step_to_wire(&r)),
            );
        }
        let batch = pb::StepBatch {
            actor_id: self.actor.clone(),
            session: SESSION,
            sequence: self.sequence,
            steps,
        };
        self.tx.send(batch).await.unwrap();
    }

    /// The learner's status, after downloading its latest snapshot if it
    /// is newer than the one held.
    async fn refreshed(&mut self, learner: &Learner) -> pb::LearnerStatus {
        let status = learner.status().await;
        if self.version() < status.latest_snapshot {
            let latest = Selector::Tag(pb::SnapshotTag::Latest.into());
            let (info, bytes) = download_snapshot(&mut self.client, latest).await.unwrap();
            let policy = network(&bytes, &learner.env);
            self.snapshot = Some((info.version, bytes, policy));
        }
        status
    }
}

/// Feeds `learner` as actor `actor` until it has made `updates` updates;
/// returns the last status.
async fn feed(learner: &Learner, actor: &str, updates: u64) -> pb::LearnerStatus {
    feed_until(learner, actor, |s| s.updates >= updates).await
}

/// Feeds `learner` as actor `actor` until its status satisfies `done`.
async fn feed_until(
    learner: &Learner,
    actor: &str,
    done: impl Fn(&pb::LearnerStatus) -> bool,
) -> pb::LearnerStatus {
    let mut feeder = Feeder::start(learner, actor).await;
    feeder.until(learner, done).await
}

/// Feeds `learner` until a snapshot published after the uniform warm-up
/// points at the target (mean cosine over eight directions above 0.8, each
/// above 0.5) and returns `margin` more on held-out episodes than random
/// actions and the `untrained` snapshot; returns the status then, that
/// snapshot's version and its bytes. Panics, with the last snapshot's figures, once the learner has
/// made `most` updates.
///
/// The tiny task's CNN policy swings between snapshots while it learns
/// (measured, learner seeds 0 to 6): at update 2,500, two of four seeds
/// pointed at the target and two did not, as much before the CPU
/// BatchNorm of issue 16 as after it; one seed's snapshots went from
/// pointing at it (update 1,019) to missing half the directions (1,532) to
/// all within 15° (2,044). Waiting for a good snapshot, the first came at
/// 1,020 to 6,524 updates, and repeated runs of one seed differ with the
/// machine's load. The set network's came at 507 to 1,020.
async fn learn(
    learner: &Learner,
    untrained: &[u8],
    margin: f64,
    most: u64,
) -> (pb::LearnerStatus, u64, Vec<u8>) {
    let env = &learner.env;
    let random = mean_return(&mut UniformRandom::new(5), env);
    let untrained = mean_return(&mut network(untrained, env), env);
    let mut feeder = Feeder::start(learner, "actor-0").await;
    let mut last = String::from("none after the warm-up");
    loop {
        let seen = feeder.version();
        let status = feeder
            .until(learner, |s| {
                (s.latest_snapshot > seen && !s.explore_uniformly) || s.updates >= most
            })
            .await;
        assert!(
            status.updates < most,
            "no snapshot learned in {most} updates; the last: {last}"
        );
        let Some((version, bytes, policy)) = &mut feeder.snapshot else {
            unreachable!("a snapshot newer than {seen} was downloaded");
        };
        let cosines = alignment(policy);
        let mean = cosines.iter().sum::<f32>() / cosines.len() as f32;
        last = format!("v{version}, cosines {cosines:?}");
        if mean > 0.8 && cosines.iter().all(|&c| c > 0.5) {
            let trained = mean_return(policy, env);
            if trained > random + margin && trained > untrained + margin {
                return (status, *version, bytes.clone());
            }
            last += &format!(
                ", mean returns: trained {trained:.0}, random {random:.0}, untrained {untrained:.0}"
            );
        }
    }
}

/// Cosine between `policy`'s action and the target vector, for target
/// vectors in eight directions with nothing else in view.
fn alignment(policy: &mut NetworkPolicy) -> Vec<f32> {
    let observations: Vec<Observation> = (0..8)
        .map(|k| {
            let angle = k as f32 * std::f32::consts::FRAC_PI_4 + 0.3;
            Observation {
                vector: [0.8 * angle.cos(), 0.8 * angle.sin()],
                ..Observation::default()
            }
        })
        .collect();
    let refs: Vec<&Observation> = observations.iter().collect();
    let mut actions = vec![Action::ZERO; refs.len()];
    policy.act(&refs, &mut actions);
    actions
        .iter()
        .zip(&observations)
        .map(|(a, o)| {
            let [x, y] = a.components();
            let [vx, vy] = o.vector;
            (x * vx + y * vy) / ((x * x + y * y).sqrt() * (vx * vx + vy * vy).sqrt() + 1e-9)
        })
        .collect()
}

/// Mean return of a policy over 32 held-out episodes of `env`.
fn mean_return(policy: &mut dyn Policy, env: &EnvConfig) -> f64 {
    let seeds: Vec<u64> = (100_000..100_032).collect();
    let episodes = evaluate(env, policy, &seeds, 32).unwrap();
    EvalSummary::of(&episodes).mean_return
}

/// The actor a published snapshot holds, acting alone as the actors
/// explore with it. A set network's snapshot carries the critics that
/// check it, a CNN's none.
fn network(snapshot: &[u8], env: &EnvConfig) -> NetworkPolicy {
    let (policy, info) =
        NetworkPolicy::from_snapshot(snapshot, env, &burn::tensor::Device::flex()).unwrap();
    let set = matches!(info.architecture, tweezer_nets::Architecture::Set(_));
    assert_eq!(
        policy.has_critics(),
        set,
        "snapshot v{} of {:?}",
        info.version,
        info.architecture
    );
    policy.actor_alone()
}

fn checkpoints(run: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(run.join("checkpoints"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "twz"))
        .collect();
    files.sort();
    files
}

/// `max_updates` stops the updates at exactly that many, with a snapshot
/// there, while the learner keeps taking steps: what `experiment train
/// --updates` judges a policy by.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn max_updates_stops_learning_at_that_many_with_a_snapshot_there() {
    let (dir, run, config) = run_dir();
    // Slack enough that the limiter never holds a batch back.
    let limited = TINY
        .replace(
            "uniform_steps = 2000",
            "uniform_steps = 2000\nmax_updates = 300",
        )
        .replace("min_size = 500", "min_size = 500\nslack = 1000000");
    std::fs::write(&config, limited).unwrap();
    let learner = Learner::fresh(dir.path(), &config, &run);
    let reached = feed(&learner, "actor-0", 300).await;
    assert_eq!(reached.updates, 300, "{reached:?}");
    // A thousand more steps owe a thousand more updates; none is made.
    let more = reached.steps_inserted + 1000;
    let held = feed_until(&learner, "actor-1", |s| s.steps_inserted >= more).await;
    assert_eq!(held.updates, 300, "{held:?}");
    // v1 is the untrained policy; the next (every 500) would be at 500.
    assert_eq!(held.latest_snapshot, 2, "{held:?}");
    let mut client = learner.client().await;
    let (info, _) = download_snapshot(&mut client, Selector::Version(2))
        .await
        .unwrap();
    assert_eq!(info.training_step, 300);
    let (exit, log) = learner.stop();
    assert!(exit.success(), "{log}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn learns_to_point_at_the_target_over_grpc() {
    let (dir, run, config) = run_dir();
    let learner = Learner::fresh(dir.path(), &config, &run);
    let mut client = learner.client().await;

    let untrained = download_snapshot(&mut client, Selector::Tag(pb::SnapshotTag::Latest.into()))
        .await
        .unwrap();
    assert_eq!(
        untrained.0.version, 1,
        "the untrained policy is published first"
    );
    assert_eq!(
        (untrained.0.image_width, untrained.0.image_height),
        (20, 16)
    );

    // In episodes the trained policy carries the sphere much of the
    // 1,000 px (return up to ~880); random actions and the untrained
    // network do not (~ -200: the time penalty, little carry).
    let (_, version, learned) = learn(&learner, &untrained.1, 500.0, 10_000).await;
    // The learner goes on updating meanwhile: the snapshot judged is asked
    // for by version.
    let (info, served) = download_snapshot(&mut client, Selector::Version(version))
        .await
        .unwrap();
    assert_eq!(info.version, version);
    assert!(served == learned, "version {version} served as downloaded");
    // Enough snapshots that the first is pruned and a later one is best.
    let status = feed_until(&learner, "actor-1", |s| s.latest_snapshot >= 6).await;
    assert!(status.steps_inserted >= 3_000, "{status:?}");
    assert!(status.buffer_size > 0 && status.buffer_capacity == 50_000);
    assert!(
        status.episodes > 0 && status.rolling_return != 0.0,
        "{status:?}"
    );
    assert!(status.best_snapshot >= 2, "{status:?}");
    assert!(status.critic_loss.is_finite() && status.mean_q.is_finite());
    let before = alignment(&mut network(&untrained.1, &learner.env));
    assert!(
        before.iter().sum::<f32>() / 8.0 < 0.5,
        "untrained cosines {before:?}"
    );

    let best_now = learner.status().await.best_snapshot;
    let best = download_snapshot(&mut client, Selector::Tag(pb::SnapshotTag::Best.into()))
        .await
        .unwrap();
    assert_eq!(best.0.version, best_now);
    let missing = download_snapshot(&mut client, Selector::Version(1)).await;
    assert!(
        matches!(&missing, Err(tweezer_proto::DownloadError::Status(s)) if s.code() == tonic::Code::NotFound),
        "version 1 is pruned (keep = 2): {missing:?}"
    );

    let (exit, log) = learner.stop();
    assert!(exit.success(), "{log}");
    assert!(log.contains("checkpoint written"), "{log}");
    assert_eq!(checkpoints(&run).len(), 1);
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    for kind in ["update", "episode", "snapshot", "checkpoint"] {
        assert!(
            metrics.contains(&format!(r#""kind":"{kind}""#)),
            "no {kind} line in the metrics"
        );
    }
    assert!(run.join("snapshots/best.safetensors").exists());
    assert!(run.join("config.toml").exists());
}

/// The tiny task for the set network, with free spheres in the field: it
/// must learn to point at the target from inputs that list them.
fn tiny_set_config() -> String {
    TINY.replace(
        "min_free_spheres = 0\nmax_free_spheres = 0",
        "min_free_spheres = 200\nmax_free_spheres = 200",
    )
    .replace(
        "[learner.td3]",
        "[learner.network]\nkind = \"set\"\n[learner.td3]",
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_set_network_learns_to_point_at_the_target_over_grpc() {
    let (dir, run, config) = run_dir();
    std::fs::write(&config, tiny_set_config()).unwrap();
    let learner = Learner::fresh(dir.path(), &config, &run);
    let env = learner.env.clone();
    assert_eq!(env.min_free_spheres, 200);
    let mut client = learner.client().await;
    let (info, untrained) =
        download_snapshot(&mut client, Selector::Tag(pb::SnapshotTag::Latest.into()))
            .await
            .unwrap();
    assert_eq!(info.architecture, "tweezer-set-actor-v1");
    assert_eq!((info.image_width, info.image_height), (0, 0));
    assert!(info.network.contains("max_spheres 32"), "{info:?}");

    let (status, ..) = learn(&learner, &untrained, 300.0, 10_000).await;
    assert!(status.episodes > 0, "{status:?}");
    let (exit, log) = learner.stop();
    assert!(exit.success(), "{log}");
    // The checkpoint names the networks: resuming it with the CNN's
    // config is refused, saying what differs.
    let cnn = dir.path().join("cnn.toml");
    std::fs::write(&cnn, TINY).unwrap();
    let security = credentials().file("server");
    let refused = tweezer_system_tests::run(
        "learner",
        &[
            "serve",
            "--resume",
            run.to_str().unwrap(),
            "--config",
            cnn.to_str().unwrap(),
            "--security",
            &security,
        ],
    );
    let err = stderr_of_failure(&refused);
    assert!(
        err.contains("architecture tweezer-set-actor-v1 vs tweezer-paper-actor-v1"),
        "{err}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn auto_resume_starts_a_run_then_continues_it() {
    let (dir, run, config) = run_dir();
    let args = [&run_args(&config, &run)[..], &["--auto-resume"]].concat();
    let learner = Learner::start(dir.path(), &args);
    let first = learner.status().await;
    let (exit, log) = learner.stop();
    assert!(exit.success(), "{log}");
    assert!(!log.contains("resuming"), "{log}");
    assert_eq!(checkpoints(&run).len(), 1);

    // As systemd, Slurm or Kubernetes would restart it: the same command.
    let learner = Learner::start(dir.path(), &args);
    let again = learner.status().await;
    assert!(again.latest_snapshot >= first.latest_snapshot);
    let (exit, log) = learner.stop();
    assert!(exit.success(), "{log}");
    assert!(log.contains("resuming"), "{log}");
    assert!(log.contains("checkpoint written"), "{log}");
    assert_eq!(
        checkpoints(&run).len(),
        1,
        "the same state, the same checkpoint"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn resumes_from_the_newest_whole_checkpoint() {
    let (dir, run, config) = run_dir();
    let learner = Learner::fresh(dir.path(), &config, &run);
    let first = feed(&learner, "actor-0", 600).await;
    let (exit, log) = learner.stop();
    assert!(exit.success(), "{log}");
    let saved = checkpoints(&run);
    assert_eq!(saved.len(), 1);

    // A fresh run may not write over it.
    let security = credentials().file("server");
    let refused = tweezer_system_tests::run(
        "learner",
        &[
            "serve",
            "--config",
            config.to_str().unwrap(),
            "--run-dir",
            run.to_str().unwrap(),
            "--security",
            &security,
        ],
    );
    assert!(stderr_of_failure(&refused).contains("--resume"));

    // A newer checkpoint cut short mid-write must be skipped.
    let whole = std::fs::read(&saved[0]).unwrap();
    let cut = run.join("checkpoints/ckpt-999999999999-999999999999.twz");
    std::fs::write(&cut, &whole[..whole.len() / 2]).unwrap();

    let learner = Learner::start(dir.path(), &["--resume", run.to_str().unwrap()]);
    let channel = connect(&learner.addr, "actor").await;
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
    let serving = health
        .check(tonic_health::pb::HealthCheckRequest {
            service: "tweezer.v1.Learner".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        serving.status(),
        tonic_health::pb::health_check_response::ServingStatus::Serving
    );
    let resumed = learner.status().await;
    assert!(
        resumed.updates >= first.updates,
        "{resumed:?} after {first:?}"
    );
    assert_eq!(resumed.steps_inserted, first.steps_inserted);
    assert!(resumed.buffer_size > 0, "the replay was checkpointed");
    assert_eq!(resumed.latest_snapshot, first.latest_snapshot);
    assert_eq!(resumed.explore_uniformly, resumed.steps_inserted < 2_000);

    // The same actor resending its last batch is acknowledged, not stored.
    let mut client = learner.client().await;
    let (tx, rx) = tokio::sync::mpsc::channel(1);
    let mut acks = client
        .stream_steps(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let mut envs = tweezer_gym::RandomSteps::new(&tiny_env(), 1, 3).unwrap();
    let steps = envs.by_ref().take(4).map(|r| step_to_wire(&r)).collect();
    tx.send(pb::StepBatch {
        actor_id: "actor-0".into(),
        session: SESSION,
        sequence: 0,
        steps,
    })
    .await
    .unwrap();
    acks.message().await.unwrap().unwrap();
    let after = learner.status().await;
    assert_eq!(after.steps_inserted, first.steps_inserted);
    assert_eq!(after.duplicate_batches, 1);
    drop(tx);

    let (exit, log) = learner.stop();
    assert!(exit.success(), "{log}");
    assert!(log.contains("skipping an unusable checkpoint"), "{log}");
    assert!(log.contains("checksum mismatch"), "{log}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sigkill_after_more_snapshots_than_kept_since_the_checkpoint_leaves_the_run_resumable() {
    let (dir, run, config) = run_dir();
    // A snapshot every 100 updates (two kept besides the best).
    let tiny = std::fs::read_to_string(&config).unwrap();
    std::fs::write(
        &config,
        tiny.replace("every_updates = 500", "every_updates = 100"),
    )
    .unwrap();
    let learner = Learner::fresh(dir.path(), &config, &run);
    feed(&learner, "actor-0", 150).await;

    // A checkpoint, taken while learning is paused so that no snapshot is
    // published in between: it needs the latest snapshot of that moment.
    let mut control = LearnerClient::new(connect(&learner.addr, "control").await);
    control
        .pause_learning(pb::PauseLearningRequest {})
        .await
        .unwrap();
    control.checkpoint(pb::CheckpointRequest {}).await.unwrap();
    let at_checkpoint = learner.status().await;
    control
        .resume_learning(pb::ResumeLearningRequest {})
        .await
        .unwrap();

    // Then more snapshots than the learner keeps, and a SIGKILL: no final
    // checkpoint.
    feed(&learner, "actor-1", at_checkpoint.updates + 400).await;
    let newest = learner.status().await.latest_snapshot;
    assert!(newest >= at_checkpoint.latest_snapshot + 3, "v{newest}");
    drop(learner);

    // The run resumes from that checkpoint, its snapshot read back.
    let learner = Learner::start(dir.path(), &["--resume", run.to_str().unwrap()]);
    let resumed = learner.status().await;
    assert_eq!(resumed.latest_snapshot, at_checkpoint.latest_snapshot);
    assert_eq!(resumed.steps_inserted, at_checkpoint.steps_inserted);
    let (exit, log) = learner.stop();
    assert!(exit.success(), "{log}");
    assert!(log.contains("resuming"), "{log}");
}

#[tokio::test(flavor = "multi_thread")]
async fn updates_that_diverge_are_rolled_back_then_learning_pauses_and_the_learner_keeps_serving() {
    // The tiny networks' state is small: the learner keeps a copy of it.
    let (_dir, run, log) = diverge_until_paused(None).await;
    assert_eq!(checkpoints(&run).len(), 1, "{log}");
}

#[tokio::test(flavor = "multi_thread")]
async fn updates_that_diverge_roll_back_to_a_checkpoint_where_the_config_says_so() {
    let (_dir, run, log) = diverge_until_paused(Some("checkpoint")).await;
    // The one written before training, to roll back to, and the last; both
    // at update 0, since every update was rolled back.
    let written = checkpoints(&run);
    assert_eq!(written.len(), 2, "{log}");
    for file in &written {
        let name = file.file_name().unwrap().to_string_lossy();
        assert!(name.starts_with("ckpt-000000000000-"), "{written:?}");
    }
    let first_written = log.find("checkpoint written").expect("a checkpoint");
    let first_diverged = log.find("an update diverged").expect("a divergence");
    assert!(first_written < first_diverged, "{log}");
    assert!(log.contains("rolled_back_to=0"), "{log}");
}

/// A learner whose every update diverges (rewards scaled past f32's
/// range), fed until it pauses, with `learner.rollback` set when given;
/// stopped once it is seen to serve still. Returns its directory, its run
/// directory and its log.
async fn diverge_until_paused(rollback: Option<&str>) -> (tempfile::TempDir, PathBuf, String) {
    let (dir, run, config) = run_dir();
    let mut tiny = TINY.replace("reward_scale = 0.1", "reward_scale = 1e38");
    if let Some(rollback) = rollback {
        tiny = tiny.replace(
            "[learner]\n",
            &format!("[learner]\nrollback = \"{rollback}\"\n"),
        );
    }
    std::fs::write(&config, tiny).unwrap();
    let learner = Learner::fresh(dir.path(), &config, &run);
    let paused = feed_until(&learner, "actor-0", |s| s.paused).await;
    assert!(paused.diverged_updates >= 5, "{paused:?}");
    assert_eq!(paused.updates, 0, "every update was rolled back");

    // Still serving: the first snapshot downloads, status answers, and a
    // SIGTERM ends the process cleanly with a checkpoint of the good
    // networks.
    let mut client = learner.client().await;
    let (info, bytes) = download_snapshot(&mut client, Selector::Version(1))
        .await
        .unwrap();
    assert_eq!((info.version, info.size_bytes), (1, bytes.len() as u64));
    assert!(learner.status().await.paused);
    let (exit, log) = learner.stop();
    assert!(exit.success(), "{log}");
    assert!(log.contains("learning is paused"), "{log}");
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    assert!(metrics.contains("\"divergence\""), "{metrics}");
    (dir, run, log)
}

/// The learner keeps freed memory 30 s for reuse: it re-executes itself
/// once, in the same process, with mimalloc's option set; an option the
/// user set is left as it is.
#[test]
fn the_learner_sets_the_allocator_s_purge_delay_unless_it_is_set() {
    for (vars, want) in [
        (&[][..], "30000"),
        (&[("MIMALLOC_PURGE_DELAY", "5000")][..], "5000"),
    ] {
        let (dir, run, config) = run_dir();
        let learner = Learner::start_with_env(dir.path(), &run_args(&config, &run), vars);
        let pid = learner.process.child().id();
        let environ = std::fs::read(format!("/proc/{pid}/environ")).unwrap();
        let option = format!("MIMALLOC_PURGE_DELAY={want}");
        assert!(
            environ
                .split(|&b| b == 0)
                .any(|var| var == option.as_bytes()),
            "{option} not in {}",
            String::from_utf8_lossy(&environ)
        );
        let (exit, log) = learner.stop();
        assert!(exit.success(), "{log}");
    }
}

/// A SIGTERM the moment the learner says it listens is caught: it stops
/// cleanly with a checkpoint instead of dying of the signal.
#[test]
fn a_sigterm_as_soon_as_the_learner_listens_stops_it_with_a_checkpoint() {
    let (dir, run, config) = run_dir();
    for _ in 0..3 {
        let learner = if !run.exists() {
            Learner::fresh(dir.path(), &config, &run)
        } else {
            Learner::start(dir.path(), &["--resume", run.to_str().unwrap()])
        };
        let (exit, log) = learner.stop();
        assert!(exit.success(), "{log}");
        assert!(log.contains("stopping: finishing the update"), "{log}");
        assert!(!checkpoints(&run).is_empty(), "{log}");
    }
}

#[test]
fn a_bad_config_is_refused_naming_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.toml");
    std::fs::write(&path, "[learner.td3]\ngamma = 1.5\n").unwrap();
    let err = stderr_of_failure(&tweezer_system_tests::run(
        "learner",
        &["serve", "--config", path.to_str().unwrap()],
    ));
    assert!(err.contains("learner.td3.gamma"), "{err}");
}

/// A learner built without a GPU feature refuses that device naming the
/// feature, before it creates the run directory.
#[test]
fn a_device_this_build_lacks_is_refused_before_the_run_directory_is_made() {
    let dir = tempfile::tempdir().unwrap();
    let (config, run) = (dir.path().join("gpu.toml"), dir.path().join("run"));
    std::fs::write(&config, "[learner]\ndevice = \"cuda\"\n").unwrap();
    let security = credentials().file("server");
    let mut args = vec!["serve", "--security", &security];
    args.extend(run_args(&config, &run));
    let err = stderr_of_failure(&tweezer_system_tests::run("learner", &args));
    assert!(err.contains("learner.device"), "{err}");
    assert!(err.contains("--features cuda"), "{err}");
    assert!(err.contains("deploy/cuda/with-llvm.sh"), "{err}");
    assert!(!run.exists(), "{err}");
}
