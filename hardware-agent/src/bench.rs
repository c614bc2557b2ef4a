//! `hardware-agent bench`: segmentation speed and detection quality on twin
//! frames of virtual episodes, at several focus and noise settings.

use serde_json::json;
use tweezer_hardware_agent::config::AgentConfig;
use tweezer_hardware_agent::twin::{
    DetectionQuality, OpticsConfig, detection_quality, episode_scene,
};

/// Focus settings measured (-1: centres dark, 1: light).
const FOCUS: [f64; 3] = [-0.8, 0.0, 0.8];
/// Noise settings: multiples of the twin's shot and read noise.
const NOISE: [f64; 2] = [1.0, 3.0];

/// Runs the benchmark and prints its figures.
pub fn run(config: &AgentConfig, frames: u64, json_out: bool) -> anyhow::Result<()> {
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
    let summary = json!({
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
    Ok(())
}
