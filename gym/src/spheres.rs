//! Free-sphere motion: a random acceleration each step, a speed limit per
//! axis, and reflection at the world's edges. Each sphere draws from its own
//! random stream, so its path depends only on the episode seed and its index.

use crate::config::EnvConfig;
use crate::rng::SplitMix64;

/// Tag of the first sphere's random stream; sphere `k` uses `SPHERE_TAG + k`.
const SPHERE_TAG: u64 = 1 << 32;

/// The motion parameters shared by every free sphere of an environment.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Motion {
    /// Largest random acceleration per axis, px/step².
    pub accel: f64,
    /// Largest speed per axis, px/step.
    pub max_speed: f64,
    /// World size; sphere centres stay in [0, w] x [0, h].
    pub world: [f64; 2],
}

impl Motion {
    /// The motion an environment configuration describes.
    pub fn for_config(config: &EnvConfig) -> Self {
        Self {
            accel: config.brownian_accel_px,
            max_speed: config.max_sphere_speed_px,
            world: config.world_px,
        }
    }
}

/// One free sphere: its state at step `t` and the stream its future
/// accelerations come from.
#[derive(Clone, Debug, PartialEq)]
pub struct FreeSphere {
    /// Centre in world px.
    pub pos: [f64; 2],
    /// Velocity in px/step.
    pub vel: [f64; 2],
    /// The step `pos` and `vel` belong to.
    pub t: u32,
    rng: SplitMix64,
}

impl FreeSphere {
    /// A sphere at a given state at step 0, whose accelerations come from
    /// stream `index` of `seed`.
    pub fn new(seed: u64, index: u32, pos: [f64; 2], vel: [f64; 2]) -> Self {
        Self {
            pos,
            vel,
            t: 0,
            rng: SplitMix64::derived(seed, SPHERE_TAG + u64::from(index)),
        }
    }

    /// Sphere `index` of episode `seed`: uniform over the world outside the
    /// clearance disc around `start`, velocity uniform within the speed limit.
    pub fn placed(seed: u64, index: u32, motion: &Motion, start: [f64; 2], clearance: f64) -> Self {
        let mut sphere = Self::new(seed, index, [0.0; 2], [0.0; 2]);
        let rng = &mut sphere.rng;
        let clearance_sq = clearance * clearance;
        loop {
            let x = rng.uniform(0.0, motion.world[0]);
            let y = rng.uniform(0.0, motion.world[1]);
            let (dx, dy) = (x - start[0], y - start[1]);
            if dx * dx + dy * dy > clearance_sq {
                sphere.pos = [x, y];
                break;
            }
        }
        let v = motion.max_speed;
        sphere.vel = [rng.uniform(-v, v), rng.uniform(-v, v)];
        sphere
    }

    /// One step of motion. One 64-bit draw gives both axes' accelerations,
    /// 32 random bits each.
    #[inline]
    pub fn advance(&mut self, motion: &Motion) {
        let bits = self.rng.next_u64();
        for (axis, half) in [bits as u32, (bits >> 32) as u32].into_iter().enumerate() {
            let unit = f64::from(half) * (1.0 / 4_294_967_296.0);
            let a = motion.accel * (2.0 * unit - 1.0);
            let mut v = (self.vel[axis] + a).clamp(-motion.max_speed, motion.max_speed);
            let mut p = self.pos[axis] + v;
            let hi = motion.world[axis];
            if p < 0.0 {
                p = -p;
                v = -v;
            } else if p > hi {
                p = 2.0 * hi - p;
                v = -v;
            }
            self.pos[axis] = p;
            self.vel[axis] = v;
        }
        self.t += 1;
    }

    /// Steps the sphere until its state belongs to step `t`.
    #[inline]
    pub fn advance_to(&mut self, t: u32, motion: &Motion) {
        while self.t < t {
            self.advance(motion);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn motion() -> Motion {
        Motion::for_config(&EnvConfig::default())
    }

    #[test]
    fn placement_respects_the_clearance_and_the_world() {
        let m = motion();
        let start = [5120.0, 4096.0];
        for k in 0..5000 {
            let s = FreeSphere::placed(9, k, &m, start, 108.0);
            let d = (s.pos[0] - start[0]).hypot(s.pos[1] - start[1]);
            assert!(d > 108.0);
            assert!((0.0..=m.world[0]).contains(&s.pos[0]));
            assert!((0.0..=m.world[1]).contains(&s.pos[1]));
            assert!(s.vel.iter().all(|v| v.abs() <= m.max_speed));
        }
    }

    #[test]
    fn speed_is_limited_and_edges_reflect() {
        let m = motion();
        let mut s = FreeSphere::new(1, 0, [1.0, m.world[1] - 1.0], [-2.0, 2.0]);
        for _ in 0..10_000 {
            let before = s.pos;
            s.advance(&m);
            for (axis, was) in before.into_iter().enumerate() {
                assert!(s.vel[axis].abs() <= m.max_speed);
                assert!((0.0..=m.world[axis]).contains(&s.pos[axis]));
                assert!((s.pos[axis] - was).abs() <= m.max_speed + 1e-12);
            }
        }
    }

    #[test]
    fn a_sphere_at_the_edge_moving_out_comes_back() {
        let m = Motion {
            accel: 0.0,
            ..motion()
        };
        let mut s = FreeSphere::new(1, 0, [0.5, 100.0], [-2.0, 0.0]);
        s.advance(&m);
        assert_eq!(s.pos, [1.5, 100.0]);
        assert_eq!(s.vel, [2.0, 0.0]);
    }

    #[test]
    fn catching_up_equals_stepping() {
        let m = motion();
        let a0 = FreeSphere::placed(5, 3, &m, [5120.0, 4096.0], 108.0);
        let mut a = a0.clone();
        let mut b = a0;
        for t in 1..=300 {
            a.advance(&m);
            if t % 37 == 0 {
                b.advance_to(t, &m);
                assert_eq!(a, b);
            }
        }
    }
}
