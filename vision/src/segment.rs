//! Sphere centres from a camera frame, as `docs/spec.md` §5 describes: Gaussian
//! blur, standardisation against the local background, a threshold above and
//! one below it (a sphere's centre looks lighter or darker than the background
//! with focus), erosion, dilation, then the outer contour of each blob, its
//! centroid, and a filter on area and circularity.
//!
//! The frame is first binned (2 x 2 by default: the sphere is 54 px across, so
//! nothing of its shape is lost) and each centre is refined on the standardised
//! image, first with a weighted centroid, then by centring a ring filter of the
//! sphere's ring radius on it (sub-pixel, and blind to a neighbour's pattern,
//! which pulls a centroid).

mod contour;
mod filters;
mod split;

use crate::camera::GrayFrame;
use contour::{Contour, trace_outer};
use serde::{Deserialize, Serialize};

/// How far the ring filter may move a single sphere's centroid, px.
const RING_REACH_PX: f64 = 3.0;

/// How frames are segmented; lengths and areas in full-resolution px.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SegmentConfig {
    /// Pixels binned per axis before anything else (1: none).
    pub bin: usize,
    /// Gaussian blur σ, px.
    pub blur_sigma_px: f64,
    /// Side of the square window whose mean is a pixel's background, px.
    pub background_px: f64,
    /// Foreground where the blurred frame is this many noise σ above the
    /// background ...
    pub upper_sigma: f64,
    /// ... or this many below it.
    pub lower_sigma: f64,
    /// ... and, either way, by at least this fraction of the background
    /// (faint debris and a sphere's halo stay background).
    pub min_contrast: f64,
    /// Erosion radius, px (rounded to binned px).
    pub erode_px: f64,
    /// Dilation radius, px (rounded to binned px).
    pub dilate_px: f64,
    /// Smallest blob area kept, px².
    pub min_area_px: f64,
    /// Largest blob area kept, px².
    pub max_area_px: f64,
    /// Smallest circularity (4π area / perimeter², 1 for a disc) kept; blobs
    /// cut by the frame's edge are exempt.
    pub min_circularity: f64,
    /// Blobs too large or not round enough for one sphere, but no larger
    /// than this many spheres, are split into spheres (touching and
    /// overlapping spheres make one blob); larger ones are dropped.
    pub max_merged: usize,
    /// Radius of a sphere's dark ring, px: merged blobs are split at the
    /// centres of the darkest rings of this radius.
    pub ring_radius_px: f64,
}

impl Default for SegmentConfig {
    fn default() -> Self {
        Self {
            bin: 2,
            blur_sigma_px: 2.0,
            background_px: 160.0,
            upper_sigma: 6.0,
            lower_sigma: 6.0,
            min_contrast: 0.1,
            erode_px: 2.0,
            dilate_px: 4.0,
            min_area_px: 1200.0,
            max_area_px: 3600.0,
            min_circularity: 0.8,
            max_merged: 4,
            ring_radius_px: 24.0,
        }
    }
}

/// A bad segmentation setting, or a frame of the wrong size.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SegmentError {
    /// A setting out of its range.
    #[error("segmentation.{field} = {value}: {why}")]
    Config {
        /// The setting.
        field: &'static str,
        /// Its value.
        value: f64,
        /// What it must be.
        why: &'static str,
    },
    /// The frame is not the size the segmenter was made for.
    #[error("frame is {got:?} px, the segmenter was set up for {want:?} px")]
    Size {
        /// The frame's width and height.
        got: [usize; 2],
        /// The expected width and height.
        want: [usize; 2],
    },
}

impl SegmentConfig {
    /// Checks every setting.
    pub fn validate(&self) -> Result<(), SegmentError> {
        let check = |field, value: f64, ok: bool, why| {
            if ok {
                Ok(())
            } else {
                Err(SegmentError::Config { field, value, why })
            }
        };
        check(
            "bin",
            self.bin as f64,
            (1..=8).contains(&self.bin),
            "must be 1..=8",
        )?;
        for (field, value) in [
            ("blur_sigma_px", self.blur_sigma_px),
            ("erode_px", self.erode_px),
            ("dilate_px", self.dilate_px),
            ("min_area_px", self.min_area_px),
            ("min_contrast", self.min_contrast),
            ("min_circularity", self.min_circularity),
        ] {
            check(
                field,
                value,
                value.is_finite() && value >= 0.0,
                "must be finite and ≥ 0",
            )?;
        }
        for (field, value) in [
            ("background_px", self.background_px),
            ("ring_radius_px", self.ring_radius_px),
            ("upper_sigma", self.upper_sigma),
            ("lower_sigma", self.lower_sigma),
        ] {
            check(
                field,
                value,
                value.is_finite() && value > 0.0,
                "must be finite and > 0",
            )?;
        }
        check(
            "max_area_px",
            self.max_area_px,
            self.max_area_px.is_finite() && self.max_area_px > self.min_area_px,
            "must be finite and above min_area_px",
        )?;
        check(
            "min_circularity",
            self.min_circularity,
            self.min_circularity <= 1.0,
            "must be at most 1",
        )
    }
}

/// One sphere found in a frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Detection {
    /// Centre, full-resolution px (pixel (x, y) spans [x, x + 1)).
    pub centre: [f64; 2],
    /// Area inside the blob's outer contour, px².
    pub area_px: f64,
    /// 4π area / perimeter².
    pub circularity: f64,
    /// Whether the blob touches the frame's edge (its centre is then biased
    /// toward the inside).
    pub clipped: bool,
}

/// Segments frames of one size, reusing its buffers from frame to frame.
#[derive(Debug)]
pub struct Segmenter {
    config: SegmentConfig,
    frame_size: [usize; 2],
    width: usize,
    height: usize,
    kernel: Vec<f32>,
    binned: Vec<f32>,
    work: Vec<f32>,
    deviation: Vec<f32>,
    mask: Vec<u8>,
    mask_work: Vec<u8>,
    sample: Vec<f32>,
    stack: Vec<u32>,
    members: Vec<u32>,
    contour: Contour,
    rings: split::RingScore,
}

impl Segmenter {
    /// A segmenter for frames of `frame_size` (width, height) px.
    pub fn new(config: SegmentConfig, frame_size: [usize; 2]) -> Result<Self, SegmentError> {
        config.validate()?;
        let (width, height) = (frame_size[0] / config.bin, frame_size[1] / config.bin);
        if width < 8 || height < 8 {
            return Err(SegmentError::Config {
                field: "bin",
                value: config.bin as f64,
                why: "leaves a frame under 8 x 8 binned px",
            });
        }
        let n = width * height;
        Ok(Self {
            kernel: filters::gaussian_kernel(config.blur_sigma_px / config.bin as f64),
            frame_size,
            width,
            height,
            binned: vec![0.0; n],
            work: vec![0.0; n],
            deviation: vec![0.0; n],
            mask: vec![0; n],
            mask_work: vec![0; n],
            sample: Vec::with_capacity(n / 5 + 1),
            stack: Vec::new(),
            members: Vec::new(),
            contour: Contour::default(),
            rings: split::RingScore::new(config.ring_radius_px / config.bin as f64),
            config,
        })
    }

    /// The spheres in `frame`, in raster order of their top edge.
    pub fn segment(&mut self, frame: &GrayFrame) -> Result<Vec<Detection>, SegmentError> {
        let got = [frame.width(), frame.height()];
        if got != self.frame_size {
            return Err(SegmentError::Size {
                got,
                want: self.frame_size,
            });
        }
        let (w, h, bin) = (self.width, self.height, self.config.bin);
        filters::bin(frame.pixels(), frame.width(), bin, w, h, &mut self.binned);
        // Blur into `deviation`, the background into `binned`, then their
        // difference into `deviation`.
        filters::blur(
            &self.binned,
            &mut self.work,
            &mut self.deviation,
            w,
            h,
            &self.kernel,
        );
        let radius = ((self.config.background_px / bin as f64 - 1.0) / 2.0)
            .round()
            .max(1.0);
        filters::box_mean(
            &self.deviation,
            &mut self.work,
            &mut self.binned,
            w,
            h,
            radius as usize,
        );
        for (d, b) in self.deviation.iter_mut().zip(&self.binned) {
            *d -= b;
        }
        let sigma = self.noise_sigma(f32::from(frame.max_value()));
        let (upper, lower) = (
            (self.config.upper_sigma as f32) * sigma,
            (self.config.lower_sigma as f32) * sigma,
        );
        let contrast = self.config.min_contrast as f32;
        for ((m, &d), &b) in self.mask.iter_mut().zip(&self.deviation).zip(&self.binned) {
            let floor = contrast * b;
            *m = u8::from(d > upper.max(floor) || d < -lower.max(floor));
        }
        let erode = (self.config.erode_px / bin as f64).round() as usize;
        let dilate = (self.config.dilate_px / bin as f64).round() as usize;
        filters::erode(&mut self.mask, &mut self.mask_work, w, h, erode);
        filters::dilate(&mut self.mask, &mut self.mask_work, w, h, dilate);
        Ok(self.blobs(sigma))
    }

    /// The noise σ of the standardised image: 1.4826 × the median absolute
    /// deviation of every fifth pixel, which the spheres barely move.
    fn noise_sigma(&mut self, max_value: f32) -> f32 {
        self.sample.clear();
        self.sample
            .extend(self.deviation.iter().step_by(5).map(|d| d.abs()));
        let middle = self.sample.len() / 2;
        let (_, median, _) = self.sample.select_nth_unstable_by(middle, f32::total_cmp);
        (1.4826 * *median).max(1e-4 * max_value)
    }

    /// Traces, measures, filters and refines each blob of the mask; marks
    /// each visited blob 2 in the mask.
    fn blobs(&mut self, sigma: f32) -> Vec<Detection> {
        let (w, h) = (self.width, self.height);
        let bin = self.config.bin as f64;
        let scale = bin * bin;
        // Binned pixel (j, i) spans full-resolution [bin j, bin (j + 1)).
        let full_resolution = |c: [f64; 2]| [(c[0] + 0.5) * bin, (c[1] + 0.5) * bin];
        let mut found = Vec::new();
        for start in 0..w * h {
            if self.mask[start] != 1 {
                continue;
            }
            let (x, y) = ((start % w) as i32, (start / w) as i32);
            trace_outer(&self.mask, w, h, [x, y], &mut self.contour);
            let clipped = self.flood(start);
            let shape = self.contour.shape();
            let area_px = shape.filled_area * scale;
            let (min, max) = (self.config.min_area_px, self.config.max_area_px);
            let single = if clipped {
                area_px >= min / 4.0 && area_px <= max
            } else {
                area_px >= min && area_px <= max && shape.circularity >= self.config.min_circularity
            };
            if !single {
                let spheres = (area_px / (min * max).sqrt()).round().max(2.0) as usize;
                if !clipped && area_px >= min && spheres <= self.config.max_merged {
                    let ring = self.config.ring_radius_px / bin;
                    let centres = self.rings.split(
                        &self.members,
                        [w, h],
                        &self.deviation,
                        (spheres, ring, 2.0 * f64::from(sigma)),
                    );
                    for centre in centres {
                        found.push(Detection {
                            centre: full_resolution(centre),
                            area_px: area_px / spheres as f64,
                            circularity: shape.circularity,
                            clipped,
                        });
                    }
                }
                continue;
            }
            let centre = if clipped {
                shape.centroid
            } else {
                let radius = (shape.filled_area / std::f64::consts::PI).sqrt() + 1.0;
                let centroid = self.refine(shape.centroid, radius, 2.0 * sigma);
                self.rings
                    .refine(centroid, RING_REACH_PX / bin, [w, h], &self.deviation)
            };
            found.push(Detection {
                centre: full_resolution(centre),
                area_px,
                circularity: shape.circularity,
                clipped,
            });
        }
        found
    }

    /// Marks the 8-connected blob containing `start` as visited (2) and
    /// lists its pixels in `members`; whether it touches the edge.
    fn flood(&mut self, start: usize) -> bool {
        let (w, h) = (self.width, self.height);
        let mut clipped = false;
        self.stack.clear();
        self.members.clear();
        self.stack.push(start as u32);
        self.mask[start] = 2;
        while let Some(p) = self.stack.pop() {
            self.members.push(p);
            let (x, y) = (p as usize % w, p as usize / w);
            clipped |= x == 0 || y == 0 || x == w - 1 || y == h - 1;
            for ny in y.saturating_sub(1)..=(y + 1).min(h - 1) {
                for nx in x.saturating_sub(1)..=(x + 1).min(w - 1) {
                    let q = ny * w + nx;
                    if self.mask[q] == 1 {
                        self.mask[q] = 2;
                        self.stack.push(q as u32);
                    }
                }
            }
        }
        clipped
    }

    /// The centroid of |deviation| above `floor` within `radius` binned px
    /// of `centre`, iterated: the blob's outline is thresholded noise, the
    /// sphere's intensity pattern is symmetric about its centre.
    fn refine(&self, mut centre: [f64; 2], radius: f64, floor: f32) -> [f64; 2] {
        let (w, h) = (self.width as i64, self.height as i64);
        for _ in 0..3 {
            let (mut sum, mut sx, mut sy) = (0.0f64, 0.0f64, 0.0f64);
            let (x0, x1) = (
                (centre[0] - radius).floor() as i64,
                (centre[0] + radius).ceil() as i64,
            );
            let (y0, y1) = (
                (centre[1] - radius).floor() as i64,
                (centre[1] + radius).ceil() as i64,
            );
            for y in y0.max(0)..=y1.min(h - 1) {
                let dy = y as f64 - centre[1];
                let row = &self.deviation[(y * w) as usize..][..w as usize];
                for x in x0.max(0)..=x1.min(w - 1) {
                    let dx = x as f64 - centre[0];
                    if dx * dx + dy * dy > radius * radius {
                        continue;
                    }
                    let weight = f64::from((row[x as usize].abs() - floor).max(0.0));
                    sum += weight;
                    sx += weight * x as f64;
                    sy += weight * y as f64;
                }
            }
            if sum <= 0.0 {
                break;
            }
            centre = [sx / sum, sy / sum];
        }
        centre
    }
}
