//! Observations → the padded sphere-set tensors the set networks take:
//! each free sphere's position relative to the trap (the FOV centre),
//! scaled by half the FOV width, and its distance, with a mask that marks
//! real spheres. No rendering: the replay's centres go in as they are.

use burn::tensor::{Device, Tensor, TensorData};

/// Features per sphere: x and y relative to the trap, and distance.
pub const SPHERE_FEATURES: usize = 3;

/// How observations become set tensors: the field of view they were made
/// in, and the most spheres a set holds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SphereSets {
    /// Field of view, px.
    pub fov_px: [f32; 2],
    /// The most spheres kept; an observation with more keeps the nearest.
    pub max_spheres: usize,
}

/// A batch of padded sets.
#[derive(Clone, Debug)]
pub struct SetBatch {
    /// `[batch, max_spheres, SPHERE_FEATURES]`, zero where padded.
    pub spheres: Tensor<3>,
    /// `[batch, max_spheres, 1]`: 1 for a sphere, 0 for padding.
    pub mask: Tensor<3>,
}

impl SphereSets {
    /// The features of `centres` (FOV px) into `features` and `mask`
    /// (`max_spheres` rows each, the nearest spheres first).
    pub fn write(&self, centres: &[[f32; 2]], features: &mut [f32], mask: &mut [f32]) {
        let half = 0.5 * self.fov_px[0];
        let trap = [0.5 * self.fov_px[0], 0.5 * self.fov_px[1]];
        let mut relative: Vec<[f32; 3]> = centres
            .iter()
            .map(|c| {
                let (dx, dy) = ((c[0] - trap[0]) / half, (c[1] - trap[1]) / half);
                [dx, dy, dx.hypot(dy)]
            })
            .collect();
        if relative.len() > self.max_spheres {
            relative.sort_by(|a, b| a[2].total_cmp(&b[2]));
            relative.truncate(self.max_spheres);
        }
        features.fill(0.0);
        mask.fill(0.0);
        for (k, f) in relative.iter().enumerate() {
            features[k * SPHERE_FEATURES..(k + 1) * SPHERE_FEATURES].copy_from_slice(f);
            mask[k] = 1.0;
        }
    }

    /// The padded sets of each observation's centres, on `device`.
    pub fn batch<'a>(
        &self,
        centres: impl ExactSizeIterator<Item = &'a [[f32; 2]]>,
        device: &Device,
    ) -> SetBatch {
        let (n, m) = (centres.len(), self.max_spheres);
        let mut features = vec![0f32; n * m * SPHERE_FEATURES];
        let mut mask = vec![0f32; n * m];
        for ((f, k), c) in features
            .chunks_exact_mut(m * SPHERE_FEATURES)
            .zip(mask.chunks_exact_mut(m))
            .zip(centres)
        {
            self.write(c, f, k);
        }
        SetBatch {
            spheres: Tensor::from_data(TensorData::new(features, [n, m, SPHERE_FEATURES]), device),
            mask: Tensor::from_data(TensorData::new(mask, [n, m, 1]), device),
        }
    }
}
