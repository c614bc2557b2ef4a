//! `hardware-agent bench`: segmentation speed and detection quality on twin
//! frames of virtual episodes, at several focus and noise settings; then
//! the control loop on the twin against the virtual environment, for the
//! greedy baseline and a trained snapshot.

#[cfg(feature = "aravis")]
mod camera_latency;
mod control_loop;

use control_loop::{Comparison, compare};
use serde_json::json;
use std::path::PathBuf;
use tweezer_gym::Baseline;
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_hardware_agent::policy_source::LoadedPolicy;
use tweezer_hardware_agent::twin::{
    DetectionQuality, OpticsConfig, detection_quality, episode_scene,
};

/// Focus settings measured (-1: centres dark, 1: light).
const FOCUS: [f64; 3] = [-0.8, 0.0, 0.8];
/// Noise settings: multiples of the twin's shot and read noise.
const NOISE: [f64; 2] = [1.0, 3.0];

/// What to measure.
pub struct BenchArgs {
    /// Frames per focus and noise setting.
    pub frames: u64,
    /// Twin and virtual episodes per policy (0: skip the loop).
    pub episodes: u64,
    /// The first episode seed.
    pub seed: u64,
    /// A trained snapshot to compare besides the greedy baseline.
    pub snapshot: Option<PathBuf>,
    /// One JSON object instead of a table.
    pub json: bool,
}

/// Measures the configured GenICam camera's frame-to-command latency in
/// each acquisition mode, `steps` steps each, and prints the figures.
#[cfg(feature = "aravis")]
pub fn camera(config: &AgentConfig, steps: usize, json_out: bool) -> anyhow::Result<()> {
    let modes = camera_latency::measure(config, steps)?;
    if json_out {
        println!(
            "{}",
            json!({"control_rate_hz": config.control.rate_hz, "camera": config.camera.genicam.camera, "modes": modes})
        );
        return Ok(());
    }
    println!(
        "camera {} at {} Hz: frame arrival to stage command, and step start to stage command",
        config.camera.genicam.camera, config.control.rate_hz
    );
    println!("acquisition        steps  frame p50  p99 ms  tick p50  p99 ms  incomplete  dropped");
    for m in &modes {
        println!(
            "{:<17}  {:>5}  {:>9.2}  {:>6.2}  {:>8.2}  {:>6.2}  {:>10}  {:>7}",
            format!("{:?}", m.acquisition),
            m.steps,
            m.frame_to_command_ms_median,
            m.frame_to_command_ms_p99,
            m.tick_to_command_ms_median,
            m.tick_to_command_ms_p99,
            m.incomplete_frames,
            m.dropped_frames
        );
    }
    Ok(())
}

/// Refuses: this build has no GenICam support.
#[cfg(not(feature = "aravis"))]
pub fn camera(_config: &AgentConfig, _steps: usize, _json_out: bool) -> anyhow::Result<()> {
    anyhow::bail!("{}", tweezer_vision::genicam::REBUILD_HINT)
}

/// Runs the benchmark and prints its figures.
pub fn run(config: &AgentConfig, args: &BenchArgs) -> anyhow::Result<()> {
    let (frames, json_out) = (args.frames, args.json);
    let scenes: Vec<_> = (0..frames)
        .map(|seed| episode_scene(&config.env, seed, 5))
        .collect();
    let mut settings = Vec::new();
    for focus in FOCUS {
        for noise in NOISE {
            let optics = OpticsConfig {
                focus,
                read_noise: config.twin.optics.read_noise * noise,
                full_well_electrons: config.twin.optics.full_well_electrons / (noise * noise),
                ..config.twin.optics.clone()
            };
            let quality = detection_quality(&optics, &config.segmentation, &scenes, 11)?;
            settings.push((focus, noise, quality));
        }
    }
    let total = |f: fn(&DetectionQuality) -> f64| settings.iter().map(|s| f(&s.2)).sum::<f64>();
    let spheres = total(|q| q.spheres as f64);
    let detections = total(|q| q.detections as f64);
    let found = total(|q| q.recall * q.spheres as f64);
    let error = total(|q| q.mean_error_px * q.recall * q.spheres as f64) / found;
    let mut times: Vec<f64> = settings.iter().map(|s| s.2.segment_ms_median).collect();
    times.sort_by(f64::total_cmp);
    let comparisons = loop_comparisons(config, args)?;
    // The figures of the trained policy when there is one.
    let headline = comparisons.last();
    let summary = json!({
        "loop_ms_p99": headline.map(|c| c.loop_ms_p99),
        "twin_success_rate": headline.map(|c| c.twin_rates.success_rate),
        "virtual_success_rate": headline.map(|c| c.virtual_rates.success_rate),
        "control_rate_hz": config.control.rate_hz,
        "policies": comparisons,
        "frame_px": config.twin.optics.size_px,
        "frames": settings.len() as u64 * frames,
        "segment_ms_median": times[times.len() / 2],
        "localisation_error_px": error,
        "isolated_localisation_error_px": total(|q| q.isolated_mean_error_px) / settings.len() as f64,
        "recall": found / spheres,
        "precision": total(|q| q.precision * q.detections as f64) / detections,
        "settings": settings.iter().map(|(focus, noise, q)| json!({
            "focus": focus, "noise": noise, "quality": q,
        })).collect::<Vec<_>>(),
    });
    if json_out {
        println!("{summary}");
        return Ok(());
    }
    println!("focus  noise  spheres  recall  precision  error px  isolated px  segment ms");
    for (focus, noise, q) in &settings {
        println!(
            "{focus:>5}  {noise:>5}  {:>7}  {:>6.4}  {:>9.4}  {:>8.3}  {:>11.3}  {:>10.2}",
            q.spheres,
            q.recall,
            q.precision,
            q.mean_error_px,
            q.isolated_mean_error_px,
            q.segment_ms_median
        );
    }
    println!(
        "all: segment_ms_median {:.2}, localisation_error_px {:.3}, recall {:.4}, precision {:.4}",
        summary["segment_ms_median"].as_f64().unwrap_or(f64::NAN),
        error,
        found / spheres,
        summary["precision"].as_f64().unwrap_or(f64::NAN),
    );
    if !comparisons.is_empty() {
        println!(
            "\ncontrol loop on the twin at {} Hz vs the virtual environment, same seeds:",
            config.control.rate_hz
        );
        println!(
            "policy                                    episodes  virtual  twin   twin/virtual  same  judged  loop p50  p99 ms  pos err px"
        );
    }
    for c in &comparisons {
        let name: String = c.policy.chars().take(40).collect();
        println!(
            "{name:<40}  {:>8}  {:>7.3}  {:>5.3}  {:>12.3}  {:>4.2}  {:>6.2}  {:>8.2}  {:>6.2}  {:>10.2}",
            c.episodes,
            c.virtual_rates.success_rate,
            c.twin_rates.success_rate,
            c.twin_over_virtual,
            c.same_outcome,
            c.judged_right,
            c.loop_ms_median,
            c.loop_ms_p99,
            c.position_error_px
        );
    }
    Ok(())
}

/// The greedy and planner baselines, then the snapshot if given, on the
/// twin and in the virtual environment.
fn loop_comparisons(config: &AgentConfig, args: &BenchArgs) -> anyhow::Result<Vec<Comparison>> {
    if args.episodes == 0 {
        return Ok(Vec::new());
    }
    let seeds: Vec<u64> = (args.seed..args.seed + args.episodes).collect();
    let records = tempfile::tempdir()?;
    let mut out = Vec::new();
    for baseline in [Baseline::Greedy, Baseline::Planner] {
        let load = || Ok(LoadedPolicy::baseline(baseline, &config.env));
        out.push(compare(config, &load, &seeds, records.path())?);
    }
    if let Some(snapshot) = &args.snapshot {
        let load = || Ok(LoadedPolicy::from_file(snapshot, &config.env)?);
        out.push(compare(config, &load, &seeds, records.path())?);
    }
    Ok(out)
}
