//! Sphere motion from consecutive centres (`docs/spec.md` §2, Observation):
//! each centre of this step is matched to one of the previous step's, and
//! its displacement over the step is the difference, relative to the sample.
//!
//! The same matcher runs wherever centres come from: the virtual
//! environment, the digital twin and the instrument's segmentation. It uses
//! only what every one of them has: the centres in FOV px and where the
//! stage stood at each step. A previous centre is predicted where it was,
//! less the stage's move, plus its own last displacement where it had one:
//! a free sphere's velocity changes by at most `brownian_accel_px` per axis
//! in a step, so a tracked sphere lands within a pixel of its prediction,
//! and a new one within its own speed (`max_sphere_speed_px` per axis) of
//! where it was. Pairs within the gate are taken closest first, each centre
//! at most once, so two spheres that pass through each other keep their
//! identities unless they also move alike. A match is also never farther
//! than the gate from where the sphere was: no displacement is one a free
//! sphere cannot make.

use crate::config::EnvConfig;

/// Matches each step's centres to the previous step's.
#[derive(Clone, Debug, PartialEq)]
pub struct SphereTracker {
    gate_px: f32,
    previous: Vec<[f32; 2]>,
    /// The previous centres' own displacements, where known.
    previous_moves: Vec<Option<[f32; 2]>>,
    previous_stage: Option<[f64; 2]>,
    /// Candidate pairs of the current step: (squared distance, now, before).
    pairs: Vec<(f32, u32, u32)>,
    taken: Vec<bool>,
}

impl SphereTracker {
    /// A tracker whose gate is twice the farthest a free sphere moves in a
    /// step (`max_sphere_speed_px` on each axis): room for a segmentation's
    /// jitter and a stage reading's lag on the instrument, exact in the
    /// virtual environment.
    pub fn for_config(config: &EnvConfig) -> Self {
        Self::with_gate(2.0 * std::f32::consts::SQRT_2 * config.max_sphere_speed_px as f32)
    }

    /// A tracker that matches centres within `gate_px` of their prediction.
    pub fn with_gate(gate_px: f32) -> Self {
        Self {
            gate_px,
            previous: Vec::new(),
            previous_moves: Vec::new(),
            previous_stage: None,
            pairs: Vec::new(),
            taken: Vec::new(),
        }
    }

    /// The farthest a matched centre lies from its prediction, px.
    pub fn gate_px(&self) -> f32 {
        self.gate_px
    }

    /// Forgets the previous step: the next step's spheres are all new.
    pub fn reset(&mut self) {
        self.previous.clear();
        self.previous_moves.clear();
        self.previous_stage = None;
    }

    /// Matches `centres` (FOV px), seen with the stage at `stage` (px in the
    /// sample's frame, the trap's position), to the previous step's, and
    /// writes one displacement per centre into `displacements`: its move
    /// since the previous step relative to the sample, px, or `None` for a
    /// sphere new to the field of view. A non-finite stage reading matches
    /// nothing and is not remembered.
    pub fn track(
        &mut self,
        centres: &[[f32; 2]],
        stage: [f64; 2],
        displacements: &mut Vec<Option<[f32; 2]>>,
    ) {
        displacements.clear();
        displacements.resize(centres.len(), None);
        let stage_ok = stage.iter().all(|v| v.is_finite());
        if let (Some(before), true) = (self.previous_stage, stage_ok) {
            let moved = [0, 1].map(|a| (stage[a] - before[a]) as f32);
            let gate_sq = self.gate_px * self.gate_px;
            self.pairs.clear();
            for (i, c) in centres.iter().enumerate() {
                for (j, p) in self.previous.iter().enumerate() {
                    let own = self.previous_moves[j].unwrap_or([0.0; 2]);
                    let step = [0, 1].map(|a| c[a] + moved[a] - p[a]);
                    let miss = [0, 1].map(|a| step[a] - own[a]);
                    let miss_sq = miss[0] * miss[0] + miss[1] * miss[1];
                    // Near its prediction, and no farther than a free sphere
                    // goes in a step (noise allowed): a match never implies
                    // a move a sphere cannot make.
                    if miss_sq <= gate_sq && step[0] * step[0] + step[1] * step[1] <= gate_sq {
                        self.pairs.push((miss_sq, i as u32, j as u32));
                    }
                }
            }
            // Closest first; ties by index, so the result is deterministic.
            self.pairs.sort_unstable_by(|a, b| {
                a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2))
            });
            self.taken.clear();
            self.taken.resize(self.previous.len(), false);
            for &(_, i, j) in &self.pairs {
                let (i, j) = (i as usize, j as usize);
                if displacements[i].is_none() && !self.taken[j] {
                    self.taken[j] = true;
                    let (c, p) = (centres[i], self.previous[j]);
                    displacements[i] = Some([0, 1].map(|a| c[a] + moved[a] - p[a]));
                }
            }
        }
        self.previous.clear();
        self.previous_moves.clear();
        if stage_ok {
            self.previous.extend_from_slice(centres);
            self.previous_moves.extend_from_slice(displacements);
            self.previous_stage = Some(stage);
        } else {
            self.previous_stage = None;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tracker() -> SphereTracker {
        SphereTracker::for_config(&EnvConfig::default())
    }

    #[test]
    fn the_first_step_has_only_new_spheres() {
        let mut t = tracker();
        let mut d = Vec::new();
        t.track(&[[10.0, 10.0], [500.0, 300.0]], [0.0, 0.0], &mut d);
        assert_eq!(d, vec![None, None]);
    }

    #[test]
    fn a_stage_move_is_taken_out_of_the_displacement() {
        let mut t = tracker();
        let mut d = Vec::new();
        t.track(&[[100.0, 100.0]], [0.0, 0.0], &mut d);
        // The stage moves +10 px in x: a still sphere shifts -10 px in the
        // FOV; this one also moved (+1.5, -2) on its own.
        t.track(&[[91.5, 98.0], [700.0, 20.0]], [10.0, 0.0], &mut d);
        assert_eq!(d, vec![Some([1.5, -2.0]), None]);
    }

    #[test]
    fn each_previous_centre_is_matched_once_closest_first() {
        let mut t = tracker();
        let mut d = Vec::new();
        t.track(&[[100.0, 100.0]], [0.0, 0.0], &mut d);
        t.track(&[[103.0, 100.0], [101.0, 100.0]], [0.0, 0.0], &mut d);
        assert_eq!(d, vec![None, Some([1.0, 0.0])]);
    }

    #[test]
    fn spheres_passing_through_each_other_keep_their_motion() {
        let mut t = tracker();
        let mut d = Vec::new();
        t.track(&[[100.0, 100.0], [104.0, 100.0]], [0.0, 0.0], &mut d);
        t.track(&[[102.0, 100.0], [102.0, 100.0]], [0.0, 0.0], &mut d);
        // Ambiguous: both lie 2 px from both; closest first, by index.
        assert_eq!(d, vec![Some([2.0, 0.0]), Some([-2.0, 0.0])]);
        // Each is predicted on its own line, so the one moving right, now
        // listed second, keeps its motion though the other is as near.
        t.track(&[[100.5, 100.0], [103.5, 100.0]], [0.0, 0.0], &mut d);
        assert_eq!(d, vec![Some([-1.5, 0.0]), Some([1.5, 0.0])]);
    }

    #[test]
    fn a_move_no_sphere_can_make_is_no_match_though_predicted() {
        let mut t = tracker();
        let mut d = Vec::new();
        t.track(&[[100.0, 100.0]], [0.0, 0.0], &mut d);
        t.track(&[[105.0, 100.0]], [0.0, 0.0], &mut d);
        assert_eq!(d, vec![Some([5.0, 0.0])]);
        // Predicted at 110, seen at 110.5: near the prediction, but 5.5 px
        // on from 105 is within the gate, so matched; then a further 6 px
        // is beyond what a sphere moves in a step, though it continues the
        // line.
        t.track(&[[110.5, 100.0]], [0.0, 0.0], &mut d);
        assert_eq!(d, vec![Some([5.5, 0.0])]);
        t.track(&[[116.5, 100.0]], [0.0, 0.0], &mut d);
        assert_eq!(d, vec![None]);
    }

    #[test]
    fn a_jump_beyond_the_gate_is_a_new_sphere() {
        let mut t = tracker();
        let mut d = Vec::new();
        t.track(&[[100.0, 100.0]], [0.0, 0.0], &mut d);
        t.track(&[[106.0, 100.0]], [0.0, 0.0], &mut d);
        assert_eq!(d, vec![None]);
    }

    #[test]
    fn a_bad_stage_reading_matches_nothing_and_reset_forgets() {
        let mut t = tracker();
        let mut d = Vec::new();
        t.track(&[[100.0, 100.0]], [0.0, 0.0], &mut d);
        t.track(&[[100.0, 100.0]], [f64::NAN, 0.0], &mut d);
        assert_eq!(d, vec![None]);
        t.track(&[[100.0, 100.0]], [0.0, 0.0], &mut d);
        assert_eq!(d, vec![None]);
        t.track(&[[100.0, 100.0]], [0.0, 0.0], &mut d);
        assert_eq!(d, vec![Some([0.0, 0.0])]);
        t.reset();
        t.track(&[[100.0, 100.0]], [0.0, 0.0], &mut d);
        assert_eq!(d, vec![None]);
    }
}
