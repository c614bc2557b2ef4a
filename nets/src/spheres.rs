//! Observations → the padded sphere-set tensors the set networks take:
//! each free sphere's position relative to the trap (the FOV centre),
//! scaled by half the width of the field the network was trained on, and
//! its distance, packed with where each lands in its set. No rendering: the
//! replay's centres go in as they are.

use crate::architecture::SetShape;
use burn::module::Module;
use burn::tensor::{Device, Int, Tensor, TensorData};

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

/// A batch of sets: every sphere of the batch packed in one matrix (the
/// per-sphere MLP runs on real spheres only), and where each lands in the
/// padded `[batch, width]` layout that pooling reads.
#[derive(Clone, Debug)]
pub struct SetBatch {
    /// `[spheres, SPHERE_FEATURES]`: every sphere of the batch, in order
    /// (one row of zeros, which no slot reads, when the batch has none).
    pub spheres: Tensor<2>,
    /// `[batch width]` (Int): for each padded slot, its row in `spheres`,
    /// or `spheres`' row count for padding (a zero row pooling appends).
    pub slots: Tensor<1, Int>,
    /// `[batch, 1]`: spheres per set, at least 1 (an empty set's sum is
    /// zero whatever it is divided by).
    pub counts: Tensor<2>,
    /// Slots per set: the largest set of the batch (at least 1).
    pub width: usize,
}

impl SetBatch {
    /// The same batch on a device without autodiff.
    pub fn valid(self) -> Self {
        Self {
            spheres: self.spheres.valid(),
            counts: self.counts.valid(),
            ..self
        }
    }

    /// Sets in the batch.
    pub fn len(&self) -> usize {
        self.counts.dims()[0]
    }

    /// Whether the batch holds no sets.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
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
        let width = sets.iter().map(Vec::len).max().unwrap_or(0).max(min_len);
        let packed = sets.iter().map(Vec::len).sum::<usize>().max(1);
        let mut features = Vec::with_capacity(packed * SPHERE_FEATURES);
        let mut slots = vec![packed as i64; sets.len() * width];
        let mut counts = Vec::with_capacity(sets.len());
        for (b, set) in sets.iter().enumerate() {
            for (k, f) in set.iter().enumerate() {
                slots[b * width + k] = (features.len() / SPHERE_FEATURES) as i64;
                features.extend_from_slice(f);
            }
            counts.push(set.len().max(1) as f32);
        }
        features.resize(packed * SPHERE_FEATURES, 0.0);
        let n = sets.len();
        SetBatch {
            spheres: Tensor::from_data(
                TensorData::new(features, [packed, SPHERE_FEATURES]),
                device,
            ),
            slots: Tensor::from_data(TensorData::new(slots, [n * width]), device),
            counts: Tensor::from_data(TensorData::new(counts, [n, 1]), device),
            width,
        }
    }
}
