//! The twin camera's optics: brightfield frames of spheres as a microscope
//! shows them. A sphere is a dark ring whose centre looks lighter or darker
//! with focus, with a faint bright halo; the frame has an illumination
//! gradient and vignetting, defocus blur, shot and read noise, and
//! out-of-focus debris.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use tweezer_config::{ConfigError, in_range};
use tweezer_gym::SplitMix64;
use tweezer_vision::GrayFrame;

/// How the twin camera renders; lengths in px, contrasts relative to the
/// local illumination.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OpticsConfig {
    /// Frame width and height.
    pub size_px: [usize; 2],
    /// Bits per pixel (8 to 16).
    pub bit_depth: u8,
    /// Illumination at the frame's centre, as a fraction of full scale.
    pub illumination: f64,
    /// Relative illumination change from the left to the right edge and
    /// from the top to the bottom edge.
    pub gradient: [f64; 2],
    /// Relative illumination loss in the corners.
    pub vignetting: f64,
    /// Focus: -1 (centres dark) to 1 (centres light); 0 shows rings alone.
    pub focus: f64,
    /// Radius of a sphere's dark ring.
    pub ring_radius_px: f64,
    /// Width (σ) of the ring.
    pub ring_width_px: f64,
    /// Depth of the ring.
    pub ring_contrast: f64,
    /// Brightness of a sphere's centre at focus 1 (darkness at -1).
    pub centre_contrast: f64,
    /// Size (σ) of the centre spot.
    pub centre_width_px: f64,
    /// Blur (σ) in focus; defocus adds twice |focus|.
    pub blur_px: f64,
    /// Photo-electrons at full scale: sets the shot noise.
    pub full_well_electrons: f64,
    /// Read noise, in grey levels.
    pub read_noise: f64,
    /// Out-of-focus debris per frame area, on average.
    pub debris_per_frame: f64,
}

impl Default for OpticsConfig {
    fn default() -> Self {
        Self {
            size_px: [1280, 1024],
            bit_depth: 8,
            illumination: 0.55,
            gradient: [0.15, -0.08],
            vignetting: 0.1,
            focus: 0.5,
            ring_radius_px: 24.0,
            ring_width_px: 2.5,
            ring_contrast: 0.35,
            centre_contrast: 0.3,
            centre_width_px: 6.0,
            blur_px: 1.0,
            full_well_electrons: 10_000.0,
            read_noise: 1.0,
            debris_per_frame: 0.5,
        }
    }
}

/// A blob of out-of-focus debris.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Debris {
    /// Centre, FOV px.
    pub centre: [f64; 2],
    /// Size (σ), px.
    pub width_px: f64,
    /// Relative contrast (negative: dark).
    pub contrast: f64,
}

impl OpticsConfig {
    /// Checks the settings; the error names the first bad one.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.size_px[0] < 64 || self.size_px[1] < 64 {
            return Err(ConfigError::invalid(
                "size_px",
                format!("{:?}: at least 64 x 64", self.size_px),
            ));
        }
        if !(8..=16).contains(&self.bit_depth) {
            return Err(ConfigError::invalid(
                "bit_depth",
                format!("{}: 8 to 16", self.bit_depth),
            ));
        }
        for (name, value, lo, hi) in [
            ("illumination", self.illumination, 0.01, 1.0),
            ("focus", self.focus, -1.0, 1.0),
            ("ring_radius_px", self.ring_radius_px, 1.0, 1000.0),
            ("ring_width_px", self.ring_width_px, 0.1, 100.0),
            ("ring_contrast", self.ring_contrast, 0.0, 1.0),
            ("centre_contrast", self.centre_contrast, 0.0, 1.0),
            ("centre_width_px", self.centre_width_px, 0.1, 100.0),
            ("blur_px", self.blur_px, 0.0, 50.0),
            ("full_well_electrons", self.full_well_electrons, 1.0, 1e9),
            ("read_noise", self.read_noise, 0.0, 1e4),
            ("debris_per_frame", self.debris_per_frame, 0.0, 100.0),
            ("vignetting", self.vignetting, 0.0, 0.9),
        ] {
            in_range(name, value, lo, hi)?;
        }
        Ok(())
    }

    /// Random debris for one frame: a Poisson count, anywhere in the frame,
    /// 15 to 40 px across (σ), faint, dark or light.
    pub fn debris(&self, rng: &mut SplitMix64) -> Vec<Debris> {
        let mut count = 0;
        let limit = (-self.debris_per_frame).exp();
        let mut product = rng.unit();
        while product > limit && count < 1000 {
            count += 1;
            product *= rng.unit();
        }
        (0..count)
            .map(|_| Debris {
                centre: [
                    rng.uniform(0.0, self.size_px[0] as f64),
                    rng.uniform(0.0, self.size_px[1] as f64),
                ],
                width_px: rng.uniform(15.0, 40.0),
                contrast: rng.uniform(0.04, 0.1) * if rng.unit() < 0.5 { -1.0 } else { 1.0 },
            })
            .collect()
    }

    /// A frame showing spheres centred at `spheres` (FOV px; the trapped one
    /// included) and `debris`; `seed` draws the noise.
    pub fn render(&self, spheres: &[[f64; 2]], debris: &[Debris], seed: u64) -> GrayFrame {
        let [w, h] = self.size_px;
        let mut relief = vec![0.0f32; w * h];
        let blur = self.blur_px + 2.0 * self.focus.abs();
        let ring_sigma = (self.ring_width_px.powi(2) + blur * blur).sqrt();
        let ring_depth = self.ring_contrast * self.ring_width_px / ring_sigma;
        let centre_sigma = (self.centre_width_px.powi(2) + blur * blur).sqrt();
        let centre_height =
            self.centre_contrast * self.focus * (self.centre_width_px / centre_sigma).powi(2);
        let halo = (
            self.ring_radius_px + 2.0 * ring_sigma,
            0.25 * ring_depth,
            ring_sigma * 1.5,
        );
        let reach = halo.0 + 3.0 * halo.2;
        for &centre in spheres {
            add_disc(&mut relief, self.size_px, centre, reach, |r| {
                let ring = (r - self.ring_radius_px) / ring_sigma;
                let spot = r / centre_sigma;
                let glow = (r - halo.0) / halo.2;
                -ring_depth * (-0.5 * ring * ring).exp()
                    + centre_height * (-0.5 * spot * spot).exp()
                    + halo.1 * (-0.5 * glow * glow).exp()
            });
        }
        for d in debris {
            add_disc(&mut relief, self.size_px, d.centre, 3.0 * d.width_px, |r| {
                let z = r / d.width_px;
                d.contrast * (-0.5 * z * z).exp()
            });
        }
        let max_value = ((1u32 << self.bit_depth) - 1) as f32;
        let electrons_per_level = self.full_well_electrons as f32 / max_value;
        let read = self.read_noise as f32;
        let mut pixels = vec![0u16; w * h];
        pixels
            .par_chunks_mut(w)
            .zip(relief.par_chunks(w))
            .enumerate()
            .for_each(|(y, (out, relief))| {
                let mut rng = SplitMix64::derived(seed, y as u64);
                let fy = (y as f64 + 0.5) / h as f64 - 0.5;
                for (x, (o, &m)) in out.iter_mut().zip(relief).enumerate() {
                    let fx = (x as f64 + 0.5) / w as f64 - 0.5;
                    let light = self.illumination
                        * (1.0 + self.gradient[0] * fx + self.gradient[1] * fy)
                        * (1.0 - 2.0 * self.vignetting * (fx * fx + fy * fy));
                    let level = (light as f32 * (1.0 + m)).max(0.0) * max_value;
                    let sigma = (level / electrons_per_level + read * read).sqrt();
                    let noisy = level + sigma * normal(&mut rng);
                    *o = noisy.round().clamp(0.0, max_value) as u16;
                }
            });
        GrayFrame::new(w, h, max_value as u16, pixels).expect("the twin frame's size is its own")
    }
}

/// Adds `profile(distance from centre)` to every pixel within `reach`.
fn add_disc(
    relief: &mut [f32],
    [w, h]: [usize; 2],
    centre: [f64; 2],
    reach: f64,
    profile: impl Fn(f64) -> f64,
) {
    let x0 = (centre[0] - reach).floor().max(0.0) as usize;
    let x1 = ((centre[0] + reach).ceil().max(0.0) as usize).min(w);
    let y0 = (centre[1] - reach).floor().max(0.0) as usize;
    let y1 = ((centre[1] + reach).ceil().max(0.0) as usize).min(h);
    for y in y0..y1 {
        let dy = y as f64 + 0.5 - centre[1];
        for x in x0..x1 {
            let dx = x as f64 + 0.5 - centre[0];
            let r = (dx * dx + dy * dy).sqrt();
            if r <= reach {
                relief[y * w + x] += profile(r) as f32;
            }
        }
    }
}

/// A standard normal draw (Box–Muller in f32: the noise needs speed, not
/// the last bit).
fn normal(rng: &mut SplitMix64) -> f32 {
    let bits = rng.next_u64();
    let u = ((bits >> 40) as f32 + 1.0) / (1u64 << 24) as f32;
    let v = (bits & 0xff_ffff) as f32 / (1u64 << 24) as f32;
    (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
}
