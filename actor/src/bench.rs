//! `actor bench`: how fast the environment steps and renders, and how fast
//! an actor acts: environments plus batched network inference.

use burn::tensor::Device;
use rayon::prelude::*;
use serde::Serialize;
use std::time::{Duration, Instant};
use tweezer_config::ConfigError;
use tweezer_gym::{
    Action, Env, EnvConfig, Frame, ImageConfig, Outcome, Policy, Renderer, UniformRandom, VecEnv,
};
use tweezer_nets::{Architecture, NetworkPolicy, Networks, SetShape, with_networks};

/// The networks an actor runs: the paper's CNN at its resolution and at the
/// quick preset's, and the lean preset's set network.
const NETWORKS: [(&str, Option<[u32; 2]>); 3] = [
    ("paper", Some([320, 256])),
    ("quick", Some([40, 32])),
    ("lean", None),
];
/// Environments per actor measured.
const ACTING_ENVS: [usize; 3] = [1, 16, 32];

/// One actor configuration's speed: environments stepped with the actions
/// of an untrained network, inferred in one batch per step.
#[derive(Debug, Serialize)]
pub struct ActingFigure {
    /// `paper`, `quick` or `lean`.
    pub network: &'static str,
    /// The architecture with its hyper-parameters.
    pub architecture: String,
    /// Environments stepped together.
    pub envs: usize,
    /// Environment steps per second, inference included.
    pub actor_steps_per_sec: f64,
    /// Share of the time spent in inference (rendering the batch's images
    /// or building its sets included); the rest steps the environments.
    pub inference_share: f64,
    /// Mean time of one inference on the first observation of an
    /// environment, input included, ms (the same for every `envs`).
    pub actor_infer_ms_batch1: f64,
    /// The same for 16 environments.
    pub actor_infer_ms_batch16: f64,
}

/// Benchmark figures; rates are medians over repetitions.
#[derive(Debug, Serialize)]
pub struct BenchReport {
    /// One environment on one core: random actions, resets and an
    /// up-to-date rendered frame after every step.
    pub env_steps_per_sec_1core: f64,
    /// Vectorised environments on every core, same work per step.
    pub env_steps_per_sec_all_cores: f64,
    /// Median time to render one observation into a cleared image, µs.
    pub render_us_median: f64,
    /// Median time to bring an image up to date from the previous step, µs.
    pub render_incremental_us_median: f64,
    /// Threads used for the all-cores figure.
    pub threads: usize,
    /// Environments stepped together for the all-cores figure.
    pub vec_envs: usize,
    /// Image resolution (width, height).
    pub resolution: [u32; 2],
    /// Repetitions each rate is the median of.
    pub repetitions: usize,
    /// Acting speed per network and number of environments (one
    /// repetition each).
    pub acting: Vec<ActingFigure>,
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    }
}

/// Steps per second of one environment on this thread, over about `span`.
fn one_core(
    config: &EnvConfig,
    renderer: &Renderer,
    span: Duration,
    seed: u64,
) -> Result<f64, ConfigError> {
    let mut env = Env::new(config.clone())?;
    let mut frame = Frame::<u8>::new(renderer);
    let mut policy = UniformRandom::new(seed);
    let mut episode = seed << 32;
    env.reset(episode);
    let start = Instant::now();
    let mut steps = 0u64;
    while start.elapsed() < span {
        for _ in 0..1000 {
            if env.outcome() != Outcome::Running {
                episode += 1;
                env.reset(episode);
            }
            env.step(policy.sample()).expect("running");
            frame
                .update(renderer, &env.observation().centres)
                .expect("frame made for this renderer");
        }
        steps += 1000;
    }
    Ok(steps as f64 / start.elapsed().as_secs_f64())
}

/// Steps per second of `n` vectorised environments on every core.
fn all_cores(
    config: &EnvConfig,
    renderer: &Renderer,
    n: usize,
    span: Duration,
    seed: u64,
) -> Result<f64, ConfigError> {
    let mut envs = VecEnv::new(config, n, seed)?;
    let mut frames: Vec<Frame<u8>> = (0..n).map(|_| Frame::new(renderer)).collect();
    let mut policy = UniformRandom::new(seed);
    let mut actions = vec![Action::ZERO; n];
    let start = Instant::now();
    let mut steps = 0u64;
    while start.elapsed() < span {
        for _ in 0..50 {
            for a in &mut actions {
                *a = policy.sample();
            }
            envs.step(&actions).expect("one action per environment");
            frames
                .par_iter_mut()
                .zip(envs.slots().par_iter())
                .for_each(|(frame, slot)| {
                    frame
                        .update(renderer, &slot.observation().centres)
                        .expect("frame made for this renderer");
                });
        }
        steps += 50 * n as u64;
    }
    Ok(steps as f64 / start.elapsed().as_secs_f64())
}

/// Median full and incremental render times over the observations of a few
/// random-action episodes.
fn render_times(config: &EnvConfig, renderer: &Renderer) -> Result<(f64, f64), ConfigError> {
    let mut env = Env::new(config.clone())?;
    let mut policy = UniformRandom::new(1);
    let mut observations = Vec::new();
    let mut seed = 0;
    while observations.len() < 5000 {
        env.reset(seed);
        seed += 1;
        while env.outcome() == Outcome::Running && observations.len() < 5000 {
            observations.push(env.observation().centres.clone());
            env.step(policy.sample()).expect("running");
        }
    }
    let mut image = vec![0u8; renderer.pixels()];
    let mut frame = Frame::<u8>::new(renderer);
    let mut full = Vec::with_capacity(observations.len());
    let mut incremental = Vec::with_capacity(observations.len());
    for centres in &observations {
        let t = Instant::now();
        renderer
            .render(centres, &mut image)
            .expect("sized for the renderer");
        full.push(t.elapsed().as_secs_f64() * 1e6);
        let t = Instant::now();
        frame
            .update(renderer, centres)
            .expect("sized for the renderer");
        incremental.push(t.elapsed().as_secs_f64() * 1e6);
    }
    std::hint::black_box((&image, frame.pixels()));
    Ok((median(full), median(incremental)))
}

/// Steps per second of each count of environments driven by an untrained
/// `network` over about `span`, and the share of the time inference took.
fn acting(
    config: &EnvConfig,
    network: (&'static str, Option<[u32; 2]>),
    span: Duration,
) -> Result<Vec<ActingFigure>, ConfigError> {
    let (name, image) = network;
    let mut config = config.clone();
    let device = Device::flex();
    let architecture = match image {
        Some([width, height]) => {
            config.image = ImageConfig { width, height };
            Architecture::Paper {
                height: height as usize,
                width: width as usize,
            }
        }
        // The lean preset's: in the goal frame, with motion (the critic's
        // action join does not touch the actor).
        None => Architecture::Set(SetShape {
            frame: tweezer_nets::Frame::Goal,
            inputs: tweezer_nets::SphereInputs::Motion,
            ..SetShape::new(config.fov_px)
        }),
    };
    let mut policy = with_networks!(architecture.networks(&config)?, |networks| {
        let actor = networks.actor(&device);
        NetworkPolicy::new(networks, actor, device.clone())
    });
    let mut infer = |n: usize| -> Result<f64, ConfigError> {
        let vec_env = VecEnv::new(&config, n, 11)?;
        let mut actions = vec![Action::ZERO; n];
        policy.act(&vec_env.observations(), &mut actions);
        let reps = 10;
        let t = Instant::now();
        for _ in 0..reps {
            policy.act(&vec_env.observations(), &mut actions);
        }
        Ok(t.elapsed().as_secs_f64() * 1e3 / reps as f64)
    };
    let (actor_infer_ms_batch1, actor_infer_ms_batch16) = (infer(1)?, infer(16)?);
    let mut figures = Vec::new();
    for envs in ACTING_ENVS {
        let mut vec_env = VecEnv::new(&config, envs, 7)?;
        let mut actions = vec![Action::ZERO; envs];
        let mut inference = Duration::ZERO;
        let mut steps = 0u64;
        let start = Instant::now();
        while start.elapsed() < span || steps == 0 {
            let t = Instant::now();
            policy.act(&vec_env.observations(), &mut actions);
            inference += t.elapsed();
            vec_env.step(&actions).expect("one action per environment");
            steps += envs as u64;
        }
        let elapsed = start.elapsed().as_secs_f64();
        figures.push(ActingFigure {
            network: name,
            architecture: architecture.to_string(),
            envs,
            actor_steps_per_sec: steps as f64 / elapsed,
            inference_share: inference.as_secs_f64() / elapsed,
            actor_infer_ms_batch1,
            actor_infer_ms_batch16,
        });
    }
    Ok(figures)
}

/// Runs every benchmark, each rate `repetitions` times for about `span`.
pub fn run(
    config: &EnvConfig,
    span: Duration,
    repetitions: usize,
) -> Result<BenchReport, ConfigError> {
    let renderer = Renderer::for_config(config)?;
    let repetitions = repetitions.max(1);
    let threads = rayon::current_num_threads();
    let vec_envs = 64 * threads;
    let single: Vec<f64> = (0..repetitions)
        .map(|r| one_core(config, &renderer, span, r as u64))
        .collect::<Result<_, _>>()?;
    let parallel: Vec<f64> = (0..repetitions)
        .map(|r| all_cores(config, &renderer, vec_envs, span, r as u64))
        .collect::<Result<_, _>>()?;
    let (render_us_median, render_incremental_us_median) = render_times(config, &renderer)?;
    let mut figures = Vec::new();
    for network in NETWORKS {
        figures.extend(acting(config, network, span)?);
    }
    Ok(BenchReport {
        env_steps_per_sec_1core: median(single),
        env_steps_per_sec_all_cores: median(parallel),
        render_us_median,
        render_incremental_us_median,
        threads,
        vec_envs,
        resolution: [config.image.width, config.image.height],
        repetitions,
        acting: figures,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_odd_and_even_counts() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(vec![4.0, 1.0, 2.0, 3.0]), 2.5);
    }

    #[test]
    fn a_short_run_reports_positive_rates() {
        let report = run(&EnvConfig::default(), Duration::from_millis(20), 1).unwrap();
        assert!(report.env_steps_per_sec_1core > 0.0);
        assert!(report.env_steps_per_sec_all_cores > 0.0);
        assert!(report.render_us_median > 0.0);
        assert_eq!(report.resolution, [320, 256]);
        assert_eq!(report.acting.len(), 9);
        for figure in &report.acting {
            assert!(figure.actor_steps_per_sec > 0.0, "{figure:?}");
            assert!((0.0..=1.0).contains(&figure.inference_share), "{figure:?}");
            assert!(figure.actor_infer_ms_batch16 > 0.0, "{figure:?}");
        }
    }
}
