//! Mirror images of sampled transitions: the same step seen with the
//! stage's x axis, y axis, both or neither reversed.
//!
//! The trap sits at the field of view's centre, the field is symmetric
//! about both axes through it, the free spheres move alike in every
//! direction and every reward depends on distances only: a step mirrored
//! about either axis, with its action and target mirrored too, is a step
//! the environment could have taken, with the same reward. Each sampled
//! step is shown in one of its four images at random, so a dodge to the
//! left also teaches the dodge to the right.

use crate::replay::SampledTransitions;
use tweezer_gym::SplitMix64;

/// Mirrors each transition of `sampled` about the axes through the centre
/// of a `fov_px` field, each axis with probability ½.
pub fn mirror(sampled: &mut SampledTransitions, fov_px: [u32; 2], rng: &mut SplitMix64) {
    let width = fov_px.map(|v| v as f32);
    for i in 0..sampled.rewards.len() {
        let bits = rng.next_u64();
        let flip = [bits & 1 == 1, bits & 2 == 2];
        for centres in [&mut sampled.centres[i], &mut sampled.next_centres[i]] {
            for c in centres.iter_mut() {
                for axis in 0..2 {
                    if flip[axis] {
                        c[axis] = width[axis] - c[axis];
                    }
                }
            }
        }
        for moved in [
            &mut sampled.displacements[i],
            &mut sampled.next_displacements[i],
        ] {
            for d in moved.iter_mut().flatten() {
                reverse(d, flip);
            }
        }
        for pairs in [
            &mut sampled.vectors,
            &mut sampled.next_vectors,
            &mut sampled.actions,
            &mut sampled.guides,
        ] {
            let row: &mut [f32; 2] = (&mut pairs[2 * i..2 * i + 2]).try_into().expect("a pair");
            reverse(row, flip);
        }
    }
}

fn reverse(v: &mut [f32; 2], flip: [bool; 2]) {
    for axis in 0..2 {
        if flip[axis] {
            v[axis] = -v[axis];
        }
    }
}
