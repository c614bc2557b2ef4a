//! Observations → the padded sphere-set tensors the set networks take:
//! each free sphere's position relative to the trap (the FOV centre),
//! scaled by half the width of the field the network was trained on, and
//! its distance, with a mask that marks real spheres. No rendering: the
//! replay's centres go in as they are.

use crate::architecture::SetShape;
use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};

/// Features per sphere: x and y relative to the trap, and distance.
pub const SPHERE_FEATURES: usize = 3;

/// How observations become set tensors.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SphereSets {
    /// Where the trap sits in this field of view, px (its centre).
    trap_px: [f32; 2],
    /// Px per unit of position: half the trained field's width.
    scale_px: f32,
    /// The most spheres kept; an observation with more keeps the nearest.
    max_spheres: usize,
}

/// A batch of padded sets.
#[derive(Clone, Debug)]
pub struct SetBatch {
    /// `[batch, n, SPHERE_FEATURES]`, zero where padded; `n` is the
    /// largest set of the batch (at least 1, at most `max_spheres`).
    pub spheres: Tensor<3>,
    /// `[batch, n, 1]`: 1 for a sphere, 0 for padding.
    pub mask: Tensor<3>,
}

impl SetBatch {
    /// The same batch on a device without autodiff.
    pub fn valid(self) -> Self {
        Self {
            spheres: self.spheres.valid(),
            mask: self.mask.valid(),
        }
    }
}

impl SphereSets {
    /// Sets for a network of `shape` seeing scenes of a `fov_px` field.
    pub fn new(shape: &SetShape, fov_px: [u32; 2]) -> Self {
        Self {
            trap_px: fov_px.map(|v| 0.5 * v as f32),
            scale_px: 0.5 * shape.fov_px[0] as f32,
            max_spheres: shape.max_spheres,
        }
    }

    /// The features of `centres` (FOV px), nearest first and at most
    /// `max_spheres`, as rows of [`SPHERE_FEATURES`].
    pub fn features(&self, centres: &[[f32; 2]]) -> Vec<[f32; SPHERE_FEATURES]> {
        let mut relative: Vec<[f32; SPHERE_FEATURES]> = centres
            .iter()
            .map(|c| {
                let dx = (c[0] - self.trap_px[0]) / self.scale_px;
                let dy = (c[1] - self.trap_px[1]) / self.scale_px;
                [dx, dy, dx.hypot(dy)]
            })
            .collect();
        if relative.len() > self.max_spheres {
            relative.sort_by(|a, b| a[2].total_cmp(&b[2]));
            relative.truncate(self.max_spheres);
        }
        relative
    }

    /// The padded sets of each observation's centres, on `device`, padded
    /// only as far as the batch's largest set.
    pub fn batch<'a>(
        &self,
        centres: impl ExactSizeIterator<Item = &'a [[f32; 2]]>,
        device: &Device,
    ) -> SetBatch {
        self.batch_padded(centres, 1, device)
    }

    /// As [`Self::batch`], padded to at least `min_len` spheres.
    pub fn batch_padded<'a>(
        &self,
        centres: impl ExactSizeIterator<Item = &'a [[f32; 2]]>,
        min_len: usize,
        device: &Device,
    ) -> SetBatch {
        let sets: Vec<_> = centres.map(|c| self.features(c)).collect();
        let n = sets.len();
        let m = sets.iter().map(Vec::len).max().unwrap_or(0).max(min_len);
        let mut features = vec![0f32; n * m * SPHERE_FEATURES];
        let mut mask = vec![0f32; n * m];
        for (b, set) in sets.iter().enumerate() {
            for (k, f) in set.iter().enumerate() {
                let row = b * m + k;
                features[row * SPHERE_FEATURES..(row + 1) * SPHERE_FEATURES].copy_from_slice(f);
                mask[row] = 1.0;
            }
        }
        SetBatch {
            spheres: Tensor::from_data(TensorData::new(features, [n, m, SPHERE_FEATURES]), device),
            mask: Tensor::from_data(TensorData::new(mask, [n, m, 1]), device),
        }
    }
}
