//! How well segmentation finds the spheres of twin frames, whose true
//! centres are known.

use super::OpticsConfig;
use serde::Serialize;
use tweezer_gym::{Env, EnvConfig, SplitMix64};
use tweezer_vision::{Detection, SegmentConfig, SegmentError, Segmenter};

/// A detection further than this from every true centre is false.
pub const MATCH_RADIUS_PX: f64 = 10.0;

/// Detection quality over a set of frames.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DetectionQuality {
    /// Frames segmented.
    pub frames: usize,
    /// True spheres wholly inside the frames.
    pub spheres: usize,
    /// Detections whose blob does not touch a frame's edge.
    pub detections: usize,
    /// Share of those spheres found within [`MATCH_RADIUS_PX`].
    pub recall: f64,
    /// Share of those detections within [`MATCH_RADIUS_PX`] of a sphere.
    pub precision: f64,
    /// Mean distance from a found sphere to its detection, px.
    pub mean_error_px: f64,
    /// The same over spheres with no other within two diameters.
    pub isolated_mean_error_px: f64,
    /// Median segmentation time per frame, ms.
    pub segment_ms_median: f64,
}

/// The spheres in view in episode `seed` of the virtual environment, after
/// `steps` steps standing still, in FOV px: the trapped sphere first.
pub fn episode_scene(config: &EnvConfig, seed: u64, steps: u32) -> Vec<[f64; 2]> {
    let mut env = Env::new(config.clone()).expect("a validated config");
    env.reset(seed);
    for _ in 0..steps {
        if env.step(tweezer_gym::Action::ZERO).is_err() {
            break;
        }
    }
    let [w, h] = config.fov_px.map(f64::from);
    let mut spheres = vec![[w / 2.0, h / 2.0]];
    spheres.extend(
        env.observation()
            .centres
            .iter()
            .map(|c| [f64::from(c[0]), f64::from(c[1])]),
    );
    spheres
}

/// Renders each scene with `optics` (noise and debris drawn from `seed`),
/// segments it, and scores the detections against the true centres.
pub fn detection_quality(
    optics: &OpticsConfig,
    segment: &SegmentConfig,
    scenes: &[Vec<[f64; 2]>],
    seed: u64,
) -> Result<DetectionQuality, SegmentError> {
    let mut segmenter = Segmenter::new(segment.clone(), optics.size_px)?;
    let [w, h] = optics.size_px.map(|v| v as f64);
    let radius = optics.ring_radius_px + 3.0;
    let (mut spheres, mut found, mut detections, mut true_detections) = (0, 0, 0, 0);
    let (mut errors, mut isolated) = (Vec::new(), Vec::new());
    let mut times = Vec::new();
    let distance =
        |a: [f64; 2], b: [f64; 2]| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt();
    let inside =
        |s: &[f64; 2]| s[0] >= radius && s[1] >= radius && s[0] <= w - radius && s[1] <= h - radius;
    for (k, scene) in scenes.iter().enumerate() {
        let mut rng = SplitMix64::derived(seed, k as u64);
        let debris = optics.debris(&mut rng);
        let frame = optics.render(scene, &debris, rng.next_u64());
        let start = std::time::Instant::now();
        let detected: Vec<Detection> = segmenter.segment(&frame)?;
        times.push(start.elapsed().as_secs_f64() * 1e3);
        for d in detected.iter().filter(|d| !d.clipped) {
            detections += 1;
            if scene
                .iter()
                .any(|&s| distance(s, d.centre) <= MATCH_RADIUS_PX)
            {
                true_detections += 1;
            }
        }
        for s in scene.iter().filter(|s| inside(s)) {
            spheres += 1;
            let nearest = detected
                .iter()
                .map(|d| distance(*s, d.centre))
                .fold(f64::INFINITY, f64::min);
            if nearest <= MATCH_RADIUS_PX {
                found += 1;
                errors.push(nearest);
                let alone = scene
                    .iter()
                    .all(|&o| o == *s || distance(o, *s) > 4.0 * radius);
                if alone {
                    isolated.push(nearest);
                }
            }
        }
    }
    let mean = |v: &[f64]| {
        if v.is_empty() {
            f64::NAN
        } else {
            v.iter().sum::<f64>() / v.len() as f64
        }
    };
    times.sort_by(f64::total_cmp);
    Ok(DetectionQuality {
        frames: scenes.len(),
        spheres,
        detections,
        recall: found as f64 / spheres.max(1) as f64,
        precision: true_detections as f64 / detections.max(1) as f64,
        mean_error_px: mean(&errors),
        isolated_mean_error_px: mean(&isolated),
        segment_ms_median: times.get(times.len() / 2).copied().unwrap_or(f64::NAN),
    })
}
