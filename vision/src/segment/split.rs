//! Splitting a blob of touching or overlapping spheres. A sphere shows as a
//! dark ring of known radius, so each pixel of the blob's bounding box is
//! scored by how dark the image is on a circle of that radius around it
//! (against circles just inside and outside it); sphere centres
//! are the strongest peaks of that score, at least most of a radius apart,
//! refined to sub-pixel by climbing the score sampled bilinearly.
//! A peak much weaker than the strongest is not a sphere (out-of-focus
//! debris merged with one, say), so a blob may yield a single centre; nor
//! is one whose circle is dark only where it crosses something dark (a
//! streak of debris), so a blob may yield none.

/// Points sampled on the ring.
const RING_SAMPLES: usize = 48;
/// Peaks closer than this fraction of the ring radius are one sphere.
const MIN_SEPARATION: f64 = 0.75;
/// A peak below this fraction of the strongest is dropped.
const MIN_RELATIVE_SCORE: f64 = 0.5;
/// A peak whose ring is dark on less than this share of its circle is not
/// a sphere: a dark streak, say, which a circle only crosses.
const MIN_COVERAGE: f64 = 0.5;

/// Scores candidate centres by how much darker the image is on a circle of
/// the ring's radius around them than on circles just inside and outside
/// it: a matched filter for a ring, which a circle around a wrong centre,
/// crossing the rings of its neighbours, does not fit.
#[derive(Debug, Clone)]
pub struct RingScore {
    /// Offsets on the ring, inside it and outside it: rounded for the
    /// search over pixels, exact for the sub-pixel refinement.
    circles: [Vec<(i64, i64)>; 3],
    exact: [Vec<[f64; 2]>; 3],
}

impl RingScore {
    /// A scorer for rings of `radius` binned px.
    pub fn new(radius: f64) -> Self {
        let gap = (radius / 4.0).max(2.0);
        let exact = |r: f64| -> Vec<[f64; 2]> {
            (0..RING_SAMPLES)
                .map(|k| {
                    let a = std::f64::consts::TAU * k as f64 / RING_SAMPLES as f64;
                    [r * a.cos(), r * a.sin()]
                })
                .collect()
        };
        let exact = [exact(radius), exact(radius - gap), exact(radius + gap)];
        let circles = exact.clone().map(|points| {
            let mut offsets: Vec<(i64, i64)> = points
                .iter()
                .map(|p| (p[0].round() as i64, p[1].round() as i64))
                .collect();
            offsets.dedup();
            offsets
        });
        Self { circles, exact }
    }

    /// How much darker the ring around pixel (x, y) is than its
    /// surroundings (samples off the image are skipped).
    fn at(&self, x: i64, y: i64, w: usize, h: usize, deviation: &[f32]) -> f64 {
        let mean = |offsets: &[(i64, i64)]| {
            let (mut sum, mut n) = (0.0f64, 0usize);
            for &(dx, dy) in offsets {
                let (sx, sy) = (x + dx, y + dy);
                if sx >= 0 && sy >= 0 && (sx as usize) < w && (sy as usize) < h {
                    sum += f64::from(deviation[sy as usize * w + sx as usize]);
                    n += 1;
                }
            }
            if n == 0 { 0.0 } else { sum / n as f64 }
        };
        let [ring, inside, outside] = &self.circles;
        0.5 * (mean(inside) + mean(outside)) - mean(ring)
    }

    /// The share of the ring around pixel (x, y) that is darker, by
    /// `margin`, than the circles just inside and outside it at the same
    /// angle: near 1 for a sphere's ring (less where a neighbour's
    /// overlaps it), small for a dark streak a circle only crosses.
    fn coverage(&self, x: i64, y: i64, [w, h]: [usize; 2], deviation: &[f32], margin: f64) -> f64 {
        let at = |p: [f64; 2]| {
            let (sx, sy) = (x + p[0].round() as i64, y + p[1].round() as i64);
            let inside = sx >= 0 && sy >= 0 && (sx as usize) < w && (sy as usize) < h;
            inside.then(|| f64::from(deviation[sy as usize * w + sx as usize]))
        };
        let [ring, inside, outside] = &self.exact;
        let (mut dark, mut seen) = (0usize, 0usize);
        for ((r, i), o) in ring.iter().zip(inside).zip(outside) {
            if let (Some(r), Some(i), Some(o)) = (at(*r), at(*i), at(*o)) {
                seen += 1;
                dark += usize::from(r < 0.5 * (i + o) - margin);
            }
        }
        if seen == 0 {
            0.0
        } else {
            dark as f64 / seen as f64
        }
    }

    /// The same at a sub-pixel centre, sampling bilinearly.
    fn at_exact(&self, c: [f64; 2], w: usize, h: usize, deviation: &[f32]) -> f64 {
        let sample = |x: f64, y: f64| -> Option<f64> {
            let (x0, y0) = (x.floor(), y.floor());
            if x0 < 0.0 || y0 < 0.0 || x0 + 1.0 >= w as f64 || y0 + 1.0 >= h as f64 {
                return None;
            }
            let (fx, fy) = (x - x0, y - y0);
            let i = y0 as usize * w + x0 as usize;
            let v = |k: usize| f64::from(deviation[k]);
            Some(
                (1.0 - fy) * ((1.0 - fx) * v(i) + fx * v(i + 1))
                    + fy * ((1.0 - fx) * v(i + w) + fx * v(i + w + 1)),
            )
        };
        let mean = |points: &[[f64; 2]]| {
            let (mut sum, mut n) = (0.0f64, 0usize);
            for p in points {
                if let Some(v) = sample(c[0] + p[0], c[1] + p[1]) {
                    sum += v;
                    n += 1;
                }
            }
            if n == 0 { 0.0 } else { sum / n as f64 }
        };
        let [ring, inside, outside] = &self.exact;
        0.5 * (mean(inside) + mean(outside)) - mean(ring)
    }

    /// Climbs the sub-pixel score from `start` in halving steps, at most
    /// `reach` binned px (a sphere's own ring is never farther: a climb
    /// that goes beyond has found a neighbour's, and `start` stands).
    pub fn refine(
        &self,
        start: [f64; 2],
        reach: f64,
        [w, h]: [usize; 2],
        deviation: &[f32],
    ) -> [f64; 2] {
        let mut c = start;
        let mut best = self.at_exact(c, w, h, deviation);
        let mut step = 0.5;
        while step >= 1.0 / 32.0 {
            let mut moved = false;
            for d in [[step, 0.0], [-step, 0.0], [0.0, step], [0.0, -step]] {
                let q = [c[0] + d[0], c[1] + d[1]];
                let score = self.at_exact(q, w, h, deviation);
                if score > best {
                    (best, c, moved) = (score, q, true);
                }
            }
            if (c[0] - start[0]).hypot(c[1] - start[1]) > reach {
                return start;
            }
            if !moved {
                step /= 2.0;
            }
        }
        c
    }

    /// Centres (binned px) of at most `k` spheres in the blob made of the
    /// pixels `members` (indices into rows of `w`) of an image `h` rows
    /// high, whose rings have the scorer's radius; a ring must be darker
    /// than its surroundings by `margin` (grey levels) on most of its
    /// circle. Every pixel of the blob's bounding box is a candidate: a
    /// ring's centre may lie in a hole of its blob.
    pub fn split(
        &self,
        members: &[u32],
        [w, h]: [usize; 2],
        deviation: &[f32],
        (k, radius, margin): (usize, f64, f64),
    ) -> Vec<[f64; 2]> {
        let (mut lo, mut hi) = ([i64::MAX; 2], [i64::MIN; 2]);
        for &p in members {
            let q = [(p as usize % w) as i64, (p as usize / w) as i64];
            for a in 0..2 {
                lo[a] = lo[a].min(q[a]);
                hi[a] = hi[a].max(q[a]);
            }
        }
        let mut scored: Vec<(f64, i64, i64)> = (lo[1]..=hi[1])
            .flat_map(|y| (lo[0]..=hi[0]).map(move |x| (x, y)))
            .map(|(x, y)| (self.at(x, y, w, h, deviation), x, y))
            .collect();
        scored.sort_by(|a, b| b.0.total_cmp(&a.0));
        let Some(&(best, ..)) = scored.first() else {
            return Vec::new();
        };
        let separation2 = (MIN_SEPARATION * radius).powi(2);
        let mut peaks: Vec<(i64, i64)> = Vec::with_capacity(k);
        for &(score, x, y) in &scored {
            if peaks.len() == k || score < MIN_RELATIVE_SCORE * best || score <= 0.0 {
                break;
            }
            let apart = peaks.iter().all(|&(px, py)| {
                let (dx, dy) = ((x - px) as f64, (y - py) as f64);
                dx * dx + dy * dy >= separation2
            });
            if apart && self.coverage(x, y, [w, h], deviation, margin) >= MIN_COVERAGE {
                peaks.push((x, y));
            }
        }
        peaks
            .into_iter()
            .map(|(x, y)| self.refine([x as f64, y as f64], 1.0, [w, h], deviation))
            .collect()
    }
}
