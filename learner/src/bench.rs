//! `learner bench`: how fast the learner's parts run on this machine.

use crate::config::LearnerConfig;
use crate::ingest::service::LearnerService;
use crate::replay::{Replay, ReplayConfig};
use crate::state::LearnerState;
use crate::training::minibatch::minibatch_tensors;
use crate::training::td3::{Td3, Td3Config};
use burn::tensor::Device;
use serde::Serialize;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::net::TcpListener;
use tweezer_config::ConfigError;
use tweezer_gym::{EnvConfig, RandomSteps, SplitMix64, StepBounds};
use tweezer_nets::{Networks, with_networks};
use tweezer_proto::pb;
use tweezer_proto::pb::learner_client::LearnerClient;
use tweezer_rpc::{ClientSecurity, LoopbackCredentials, Security, ServerSecurity};

/// Benchmark figures. Times are means over the timed repetitions.
#[derive(Debug, Serialize)]
pub struct LearnerBench {
    /// The networks timed, with their hyper-parameters.
    pub architecture: String,
    /// The device the networks ran on (`learner.device`): `flex`, or
    /// `cuda` or `wgpu` with the name of the GPU Burn opened.
    pub device: String,
    /// One full TD3 update at `batch_size`: sampling, the inputs (images
    /// rendered or sets built), the critic
    /// step, and the actor step with soft updates every second update;
    /// averaged over an even number of consecutive updates.
    pub update_ms_mean: f64,
    /// The critic part of an update.
    pub critic_step_ms: f64,
    /// The actor part of the updates that have one.
    pub actor_step_ms: f64,
    /// Actor inference without autodiff, batch 1.
    pub actor_infer_ms_batch1: f64,
    /// Actor inference without autodiff, batch 16.
    pub actor_infer_ms_batch16: f64,
    /// Replay memory per transition, on a replay filled to capacity with
    /// random-policy steps.
    pub replay_bytes_per_transition: f64,
    /// Capacity of that replay.
    pub replay_capacity: usize,
    /// Image resolution (width, height) of the environment.
    pub resolution: [u32; 2],
    /// Transitions per update (`learner.batch_size`).
    pub batch_size: usize,
    /// Updates timed.
    pub updates_timed: usize,
    /// Transitions per second taken in over real gRPC on loopback from 8
    /// concurrent actor streams, learner updates paused: TLS and tokens, as
    /// deployed.
    pub ingest_transitions_per_sec: f64,
    /// The same over plain TCP (tokens still checked).
    pub ingest_plaintext_transitions_per_sec: f64,
}

/// The networks' share of the figures.
struct NetworkTimes {
    update_ms_mean: f64,
    critic_step_ms: f64,
    actor_step_ms: f64,
    actor_infer_ms_batch1: f64,
    actor_infer_ms_batch16: f64,
    updates_timed: usize,
}

/// Times TD3 updates and inference of the networks on batches of `replay`.
struct TimeNetworks<'a> {
    td3: Td3Config,
    replay: &'a Replay,
    batch_size: usize,
    updates: usize,
    device: &'a Device,
}

impl TimeNetworks<'_> {
    fn time<N: Networks>(self, networks: N) -> anyhow::Result<NetworkTimes> {
        let TimeNetworks {
            td3,
            replay,
            batch_size,
            updates,
            device,
        } = self;
        let training = device.clone().autodiff();
        let mut td3 = Td3::new(td3, networks.clone(), &training)?;
        let mut rng = SplitMix64::new(7);
        let mut sample = |n: usize, on: &Device| {
            let sampled = replay.sample(n, &mut rng).expect("the replay is full");
            minibatch_tensors(&sampled, &networks, on)
        };
        // Two warm-up updates, then `updates` timed ones, each step timed on
        // its own; sampling and building the inputs count.
        td3.update(sample(batch_size, &training));
        td3.update(sample(batch_size, &training));
        let updates = updates.max(2).next_multiple_of(2);
        let (mut critic, mut actor) = (Vec::new(), Vec::new());
        let started = Instant::now();
        for _ in 0..updates {
            let batch = sample(batch_size, &training);
            let step = Instant::now();
            td3.critic_step(&batch);
            critic.push(step.elapsed().as_secs_f64() * 1e3);
            if td3.actor_due() {
                let step = Instant::now();
                td3.actor_step(batch);
                actor.push(step.elapsed().as_secs_f64() * 1e3);
            }
        }
        let update_ms_mean = started.elapsed().as_secs_f64() * 1e3 / updates as f64;

        let policy = td3.policy();
        let mut infer = |n: usize| {
            let batch = sample(n, device);
            time_ms(10, || {
                let action = N::act(&policy, batch.input.clone(), batch.vector.clone());
                std::hint::black_box(action.into_data());
            })
        };
        Ok(NetworkTimes {
            update_ms_mean,
            critic_step_ms: mean(&critic),
            actor_step_ms: mean(&actor),
            actor_infer_ms_batch1: infer(1),
            actor_infer_ms_batch16: infer(16),
            updates_timed: updates,
        })
    }
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// Fills a replay of `capacity` transitions from random-policy episodes.
fn filled_replay(env: &EnvConfig, capacity: usize) -> Result<Replay, ConfigError> {
    let mut replay = Replay::new(ReplayConfig {
        capacity,
        ..ReplayConfig::default()
    });
    for record in RandomSteps::new(env, 64, 1)? {
        if replay.len() >= capacity {
            break;
        }
        replay
            .insert(0, &record)
            .expect("environment observations fit a record");
    }
    Ok(replay)
}

/// `count` batches of `size` consecutive random-policy steps from `envs`
/// environments, as actor `actor` would send them: the ingest benchmark's
/// load, and the tests'.
pub fn random_batches(
    env: &EnvConfig,
    actor: &str,
    envs: usize,
    count: usize,
    size: usize,
    seed: u64,
) -> Result<Vec<pb::StepBatch>, ConfigError> {
    let mut steps = RandomSteps::new(env, envs, seed)?.map(|r| tweezer_proto::step_to_wire(&r));
    Ok((0..count)
        .map(|sequence| pb::StepBatch {
            actor_id: actor.to_string(),
            session: seed.wrapping_add(1),
            sequence: sequence as u64,
            steps: steps.by_ref().take(size).collect(),
        })
        .collect())
}

/// Transitions per second through 8 concurrent `StreamSteps` calls on
/// loopback into a replay of the paper's capacity, without rate limiting,
/// secured by the security files `server` and `client`.
fn ingest_rate(env: &EnvConfig, server: &Path, client: &Path) -> anyhow::Result<f64> {
    let server = ServerSecurity::load(&Security::load(Some(server))?)?;
    let client = ClientSecurity::load(&Security::load(Some(client))?)?;
    let streams = 8;
    let per_stream: Vec<Vec<pb::StepBatch>> = (0..streams)
        .map(|k| random_batches(env, &format!("bench-{k}"), 16, 40, 256, k))
        .collect::<Result<_, _>>()?;
    let total: usize = per_stream.iter().flatten().map(|b| b.steps.len()).sum();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        let ingest = Arc::new(LearnerState::new(
            Replay::new(ReplayConfig::default()),
            None,
            StepBounds::for_config(env),
        ));
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?.to_string();
        let service = LearnerService::new(ingest.clone()).into_server();
        tokio::spawn(server.serve(listener, service, std::future::pending()));
        let started = Instant::now();
        let tasks: Vec<_> = per_stream
            .into_iter()
            .map(|sent| {
                let (client, addr) = (client.clone(), addr.clone());
                tokio::spawn(async move {
                    let channel = client.connect(&addr, Duration::from_secs(10)).await?;
                    let mut client = LearnerClient::new(channel);
                    let mut acks = client
                        .stream_steps(tokio_stream::iter(sent))
                        .await?
                        .into_inner();
                    while acks.message().await?.is_some() {}
                    anyhow::Ok(())
                })
            })
            .collect();
        for task in tasks {
            task.await??;
        }
        let rate = total as f64 / started.elapsed().as_secs_f64();
        anyhow::ensure!(
            ingest.replay().inserted() as usize + 16 * streams as usize >= total,
            "not every transition arrived"
        );
        Ok(rate)
    })
}

/// Mean time of `f` over `reps` calls after one warm-up call, ms.
fn time_ms(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
    let start = Instant::now();
    for _ in 0..reps {
        f();
    }
    start.elapsed().as_secs_f64() * 1e3 / reps as f64
}

/// Runs every benchmark: `updates` (rounded up to even) timed TD3 updates
/// of the networks `learner.network` configures, with `learner.td3` at
/// `learner.batch_size`, on `learner.device`, after two warm-up updates, on
/// a replay of `capacity` transitions.
pub fn run(
    env: &EnvConfig,
    learner: &LearnerConfig,
    capacity: usize,
    updates: usize,
) -> anyhow::Result<LearnerBench> {
    let (network, choice, batch_size) = (&learner.network, learner.device, learner.batch_size);
    let device = &choice.device()?;
    let replay = filled_replay(env, capacity)?;
    let settings = TimeNetworks {
        td3: learner.td3.clone(),
        replay: &replay,
        batch_size,
        updates,
        device,
    };
    let networks = with_networks!(network.architecture(env).networks(env)?, |networks| {
        settings.time(networks)
    })?;
    // The ingest runs secured as deployed: the run's credentials, and
    // plaintext files beside them.
    let dir = tempfile::tempdir()?;
    let security = dir.path().to_path_buf();
    let credentials = LoopbackCredentials::provision(&security)?;
    let plain_server = security.join("plain-learner.toml");
    let plain_client = security.join("plain-actor.toml");
    std::fs::write(&plain_server, "plaintext = true\ntokens = \"tokens\"\n")?;
    std::fs::write(
        &plain_client,
        "plaintext = true\ntoken_file = \"actor.token\"\n",
    )?;
    Ok(LearnerBench {
        architecture: network.architecture(env).to_string(),
        device: choice.describe(device),
        update_ms_mean: networks.update_ms_mean,
        critic_step_ms: networks.critic_step_ms,
        actor_step_ms: networks.actor_step_ms,
        actor_infer_ms_batch1: networks.actor_infer_ms_batch1,
        actor_infer_ms_batch16: networks.actor_infer_ms_batch16,
        replay_bytes_per_transition: replay.bytes() as f64 / replay.len() as f64,
        replay_capacity: capacity,
        resolution: [env.image.width, env.image.height],
        batch_size,
        updates_timed: networks.updates_timed,
        ingest_transitions_per_sec: ingest_rate(env, &credentials.learner, &credentials.actor)?,
        ingest_plaintext_transitions_per_sec: ingest_rate(env, &plain_server, &plain_client)?,
    })
}
