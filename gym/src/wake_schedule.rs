//! Which free spheres need simulating at each step.
//!
//! A sphere matters only when it is inside the *near box*: the FOV grown by a
//! sphere radius, around the trap. Spheres outside it are parked and not
//! stepped at all; each one is brought up to date from its own random stream
//! when it could possibly have reached the box, so the simulation's results
//! are exactly those of stepping every sphere every step.
//!
//! The bound: a sphere last stepped at `t₁` at `p₁` moves at most `v` px per
//! step per axis, and the trap stays within `reach` (L∞) of an *anchor* point
//! `A`. The box gap is 1-Lipschitz in L∞, so the sphere can be near at step
//! `t` only if `v·t + reach ≥ gap(p₁ − A) + v·t₁`. The left side is a clock
//! that never runs backward while the anchor stays, so parked spheres sit on
//! a wheel keyed by the right side and wake when the clock reaches them. When
//! the trap has gone `REANCHOR_PX` from the anchor, the anchor moves to the
//! trap and every parked sphere is re-keyed from its stored state, without
//! stepping it.

use crate::config::EnvConfig;
use crate::num;
use crate::spheres::{FreeSphere, Motion};

/// How far the trap may go from the anchor before the anchor follows it, px.
/// Smaller re-keys more often; larger keeps more spheres awake behind the trap.
const REANCHOR_PX: f64 = 128.0;

/// The schedule of free-sphere simulation for one environment.
#[derive(Clone, Debug)]
pub(crate) struct WakeSchedule {
    /// Half size of the near box.
    near_half: [f64; 2],
    /// Largest sphere speed per axis, px/step.
    speed: f64,
    /// Key width of one wheel bucket (≥ the clock's advance per step).
    bucket: f64,
    anchor: [f64; 2],
    /// Largest L∞ distance of the trap from the anchor since anchoring.
    reach: f64,
    /// `wheel[b]`: parked spheres with key in [b·bucket, (b + 1)·bucket).
    wheel: Vec<Vec<u32>>,
    /// Buckets below this have been woken in this anchor's epoch.
    swept: usize,
    /// Spheres stepped every step: near now, or possibly near next step.
    awake: Vec<u32>,
    next: Vec<u32>,
}

/// How far `d` (a sphere's offset from a box centre) lies outside a box of
/// half size `half`, in L∞; ≤ 0 inside.
#[inline]
fn gap(d: [f64; 2], half: [f64; 2]) -> f64 {
    (d[0].abs() - half[0]).max(d[1].abs() - half[1])
}

impl WakeSchedule {
    pub(crate) fn new(config: &EnvConfig) -> Self {
        let radius = config.sphere_radius_px();
        let speed = config.max_sphere_speed_px;
        let bucket = speed.max(1.0);
        // The clock never exceeds speed·time_limit plus the reach allowed
        // before re-anchoring (which may overshoot by one stage step).
        let horizon = speed * f64::from(config.time_limit) + REANCHOR_PX + config.stage_speed_px;
        let buckets = (horizon / bucket) as usize + 2;
        Self {
            near_half: [
                0.5 * f64::from(config.fov_px[0]) + radius,
                0.5 * f64::from(config.fov_px[1]) + radius,
            ],
            speed,
            bucket,
            anchor: [0.0; 2],
            reach: 0.0,
            wheel: vec![Vec::new(); buckets],
            swept: 0,
            awake: Vec::new(),
            next: Vec::new(),
        }
    }

    /// Spheres that may be near the trap (a superset of those that are).
    pub(crate) fn awake(&self) -> &[u32] {
        &self.awake
    }

    /// Starts watching an episode at step 0 with the trap at `trap`.
    pub(crate) fn start(&mut self, spheres: &[FreeSphere], trap: [f64; 2]) {
        self.anchor_at(spheres, trap, 0);
    }

    /// Moves the anchor to the trap and re-files every sphere.
    fn anchor_at(&mut self, spheres: &[FreeSphere], trap: [f64; 2], t: u32) {
        // Buckets below `swept` were emptied as they were woken.
        let first = self.swept.min(self.wheel.len());
        for bucket in &mut self.wheel[first..] {
            bucket.clear();
        }
        self.anchor = trap;
        self.reach = 0.0;
        let clock = self.speed * f64::from(t);
        self.swept = num::floor(clock / self.bucket) as usize + 1;
        self.next.clear();
        for k in 0..spheres.len() as u32 {
            self.file(spheres, k, t, trap, clock);
        }
        std::mem::swap(&mut self.awake, &mut self.next);
        self.next.clear();
    }

    /// Files sphere `k` as awake, or on the wheel at the bucket of its key.
    #[inline]
    fn file(&mut self, spheres: &[FreeSphere], k: u32, t: u32, trap: [f64; 2], clock: f64) {
        let s = &spheres[k as usize];
        let sub = |p: [f64; 2], q: [f64; 2]| [p[0] - q[0], p[1] - q[1]];
        if s.t == t && gap(sub(s.pos, trap), self.near_half) <= 0.0 {
            self.next.push(k);
            return;
        }
        let key = gap(sub(s.pos, self.anchor), self.near_half) + self.speed * f64::from(s.t);
        if key <= clock + self.bucket {
            // Could be near at the next step.
            self.next.push(k);
            return;
        }
        let b = num::floor(key / self.bucket);
        if let Some(bucket) = self.wheel.get_mut(b as usize) {
            bucket.push(k);
        }
        // Else the clock cannot reach it before the episode ends, unless a
        // re-anchoring brings it closer, which re-files it.
    }

    /// After the trap has moved to `trap` at step `t`: steps the awake
    /// spheres and those whose time has come to `t` and re-files them.
    pub(crate) fn refresh(
        &mut self,
        spheres: &mut [FreeSphere],
        motion: &Motion,
        trap: [f64; 2],
        t: u32,
    ) {
        let moved = (trap[0] - self.anchor[0])
            .abs()
            .max((trap[1] - self.anchor[1]).abs());
        self.reach = self.reach.max(moved);
        let clock = self.speed * f64::from(t) + self.reach;
        let awake = std::mem::take(&mut self.awake);
        for &k in &awake {
            spheres[k as usize].advance_to(t, motion);
            self.file(spheres, k, t, trap, clock);
        }
        let last = (num::floor(clock / self.bucket) as usize).min(self.wheel.len() - 1);
        while self.swept <= last {
            let due = std::mem::take(&mut self.wheel[self.swept]);
            for &k in &due {
                spheres[k as usize].advance_to(t, motion);
                self.file(spheres, k, t, trap, clock);
            }
            self.wheel[self.swept] = due;
            self.wheel[self.swept].clear();
            self.swept += 1;
        }
        self.awake = std::mem::replace(&mut self.next, awake);
        self.next.clear();
        if self.reach > REANCHOR_PX {
            self.anchor_at(spheres, trap, t);
        }
    }
}
