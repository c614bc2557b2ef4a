//! `hardware-agent bench --camera`: the configured GenICam camera's
//! frame-to-command latency in each acquisition mode. Each step does the
//! control loop's work on a live frame (segmentation, the planner's action
//! toward a fixed target) and commands the twin's simulated stages over
//! APT, at the control rate. The loop itself needs a trapped sphere in the
//! frame, which a test camera's own pattern does not show; on the
//! instrument, `run` and `serve` record the same latency per step.

use anyhow::Context;
use kdc101::StagePair;
use serde::Serialize;
use serialport::TTYPort;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tweezer_gym::{Action, Baseline, Observation};
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_hardware_agent::control::LoopTiming;
use tweezer_hardware_agent::policy_source::LoadedPolicy;
use tweezer_hardware_agent::twin::TwinStages;
use tweezer_vision::genicam::{Acquisition, GenicamCamera};
use tweezer_vision::{Camera, FrameCounters, Segmenter};

/// One acquisition mode's figures.
#[derive(Debug, Serialize)]
pub struct ModeLatency {
    /// The mode.
    pub acquisition: Acquisition,
    /// Steps measured.
    pub steps: usize,
    /// From the frame's arrival to the command, ms: median.
    pub frame_to_command_ms_median: f64,
    /// Its 99th percentile.
    pub frame_to_command_ms_p99: f64,
    /// From the step's start (the tick) to the command, ms: median.
    pub tick_to_command_ms_median: f64,
    /// Its 99th percentile.
    pub tick_to_command_ms_p99: f64,
    /// Frames that arrived incomplete.
    pub incomplete_frames: u64,
    /// Frames the camera sent that never arrived.
    pub dropped_frames: u64,
}

/// Measures both modes, `steps` steps each, at the configured control rate.
pub fn measure(config: &AgentConfig, steps: usize) -> anyhow::Result<Vec<ModeLatency>> {
    [Acquisition::FreeRun, Acquisition::SoftwareTrigger]
        .into_iter()
        .map(|acquisition| measure_mode(config, acquisition, steps))
        .collect()
}

fn measure_mode(
    config: &AgentConfig,
    acquisition: Acquisition,
    steps: usize,
) -> anyhow::Result<ModeLatency> {
    let period = Duration::from_secs_f64(config.control.period_s());
    let counters = Arc::new(FrameCounters::default());
    let genicam = tweezer_vision::genicam::GenicamConfig {
        acquisition,
        ..config.camera.genicam.clone()
    };
    let mut camera = GenicamCamera::open(&genicam, period, counters.clone())?;
    let twin = TwinStages::spawn(&config.twin).context("cannot start the twin's stages")?;
    let (mut stages, _) = StagePair::<TTYPort>::open_paths(
        twin.ports(),
        &config.stages,
        config.control.command_interval(),
    )?;
    let mut segmenter = Segmenter::new(config.segmentation.clone(), camera.size())?;
    let mut policy = LoadedPolicy::baseline(Baseline::Planner, &config.env);
    let speed = config.control.px_per_step * config.control.rate_hz;
    let mut observation = Observation {
        vector: [1.0, 0.0],
        ..Observation::default()
    };
    let mut action = [Action::ZERO];
    let (mut from_frame, mut from_tick) = (Vec::new(), Vec::new());
    camera.start()?;
    let mut next = Instant::now();
    for _ in 0..steps {
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
        let tick = Instant::now();
        let frame = camera.grab()?;
        let arrived = camera.captured().unwrap_or(tick);
        observation.centres.clear();
        observation.centres.extend(
            segmenter
                .segment(&frame)?
                .iter()
                .map(|d| d.centre.map(|v| v as f32)),
        );
        policy.policy.act(&[&observation], &mut action);
        let [ax, ay] = action[0].components();
        // Half speed one way, then back: the stages stay near the middle.
        let sign = if from_tick.len() % 2 == 0 { 0.5 } else { -0.5 };
        stages.set_velocity_px([f64::from(ax) * speed * sign, f64::from(ay) * speed * sign])?;
        from_frame.push(arrived.elapsed().as_secs_f64() * 1000.0);
        from_tick.push(tick.elapsed().as_secs_f64() * 1000.0);
        next += period;
    }
    camera.stop();
    stages.set_velocity_px([0.0; 2])?;
    let [_, incomplete_frames, dropped_frames] = counters.read();
    let from_frame = LoopTiming::of(&mut from_frame, 0.0, 1);
    let from_tick = LoopTiming::of(&mut from_tick, 0.0, 1);
    Ok(ModeLatency {
        acquisition,
        steps,
        frame_to_command_ms_median: from_frame.latency_ms_median,
        frame_to_command_ms_p99: from_frame.latency_ms_p99,
        tick_to_command_ms_median: from_tick.latency_ms_median,
        tick_to_command_ms_p99: from_tick.latency_ms_p99,
        incomplete_frames,
        dropped_frames,
    })
}
