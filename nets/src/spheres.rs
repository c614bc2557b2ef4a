//! Observations → the padded sphere-set tensors the set networks take:
//! each free sphere's position relative to the trap (the FOV centre),
//! scaled by half the width of the field the network was trained on, and
//! its distance; with [`SphereInputs::Motion`], also its displacement since
//! the previous step and whether it is new to the view; with
//! [`SphereInputs::Goal`], also the offset and displacement in the frame
//! that points at the target; in [`Frame::Goal`], every offset and
//! displacement along and across the heading to the target. Packed with
//! where each lands in its set, and each scene's heading. No rendering: the
//! replay's centres go in as they are.

use crate::architecture::{Frame, SetShape, SphereInputs};
use crate::goal_frame::to_goal;
use burn::module::Module;
use burn::tensor::{Device, Int, Tensor, TensorData};
use tweezer_gym::Observation;

/// What a network reads of one observation besides the target vector.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scene<'a> {
    /// Free spheres' centres, FOV px.
    pub centres: &'a [[f32; 2]],
    /// Their displacements since the previous step (`None`: new to the
    /// view); empty where none are known.
    pub displacements: &'a [Option<[f32; 2]>],
    /// The target vector.
    pub vector: [f32; 2],
}

impl<'a> Scene<'a> {
    /// The scene of an observation.
    pub fn of(observation: &'a Observation) -> Self {
        Self::new(
            &observation.centres,
            &observation.displacements,
            observation.vector,
        )
    }

    /// Centres with their displacements, and the target vector.
    pub fn new(
        centres: &'a [[f32; 2]],
        displacements: &'a [Option<[f32; 2]>],
        vector: [f32; 2],
    ) -> Self {
        Self {
            centres,
            displacements,
            vector,
        }
    }

    /// Centres whose motion is unknown, the target straight to the right.
    pub fn without_motion(centres: &'a [[f32; 2]]) -> Self {
        Self::new(centres, &[], [1.0, 0.0])
    }

    /// The unit vector towards the target; x where the trap is on it.
    pub(crate) fn heading(&self) -> [f32; 2] {
        let [x, y] = self.vector;
        let norm = x.hypot(y);
        if norm > 1e-6 && norm.is_finite() {
            [x / norm, y / norm]
        } else {
            [1.0, 0.0]
        }
    }

    fn displacement(&self, index: usize) -> Option<[f32; 2]> {
        tweezer_gym::displacement_at(self.displacements, index)
    }
}

/// How observations become set tensors.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SphereSets {
    /// Where the trap sits in this field of view, px (its centre).
    trap_px: [f32; 2],
    /// Px per unit of position: half the trained field's width.
    scale_px: f32,
    /// Px per unit of displacement: [`SetShape::motion_unit_px`].
    motion_unit_px: f32,
    /// The most spheres kept; an observation with more keeps the nearest.
    max_spheres: usize,
    /// What each sphere's row holds.
    inputs: SphereInputs,
    /// The axes positions and displacements are given along.
    frame: Frame,
}

/// A batch of sets: every sphere of the batch packed in one matrix (the
/// per-sphere MLP runs on real spheres only), and where each lands in the
/// padded `[batch, width]` layout that pooling reads.
#[derive(Clone, Debug)]
pub struct SetBatch {
    /// `[spheres, features]`: every sphere of the batch, in order
    /// (one row of zeros, which no slot reads, when the batch has none).
    pub spheres: Tensor<2>,
    /// `[batch width]` (Int): for each padded slot, its row in `spheres`,
    /// or `spheres`' row count for padding (a zero row pooling appends).
    pub slots: Tensor<1, Int>,
    /// `[spheres]` (Int): the set each row of `spheres` belongs to, so that
    /// a per-set value (a critic's action) can join each of its spheres;
    /// the batch's size for the zero row of a batch without spheres (a
    /// row appended to the per-set values).
    pub owners: Tensor<1, Int>,
    /// `[batch, 1]`: spheres per set, at least 1 (an empty set's sum is
    /// zero whatever it is divided by).
    pub counts: Tensor<2>,
    /// Slots per set: the largest set of the batch (at least 1).
    pub width: usize,
    /// `[batch, 2]`: each scene's unit vector towards the target, the x
    /// axis of [`Frame::Goal`].
    pub heading: Tensor<2>,
}

impl SetBatch {
    /// The same batch on a device without autodiff.
    pub fn valid(self) -> Self {
        Self {
            spheres: self.spheres.valid(),
            counts: self.counts.valid(),
            heading: self.heading.valid(),
            ..self
        }
    }

    /// The same layout with each per-sphere row mapped by `f` (to
    /// `[spheres, any]`).
    pub fn map_spheres(self, f: impl FnOnce(Tensor<2>) -> Tensor<2>) -> Self {
        Self {
            spheres: f(self.spheres),
            ..self
        }
    }

    /// Each sphere's offset from the trap, in the network's frame: the
    /// first two values of its row, as [`SphereSets::features`] lays it
    /// out. `[spheres, 2]`.
    pub(crate) fn offsets(&self) -> Tensor<2> {
        self.spheres.clone().narrow(1, 0, 2)
    }

    /// Each sphere's displacement over [`SetShape::motion_unit_px`], in the
    /// network's frame (zero for one new to the view): the two values
    /// after its distance, where rows carry motion. `[spheres, 2]`.
    pub(crate) fn motions(&self) -> Tensor<2> {
        self.spheres.clone().narrow(1, 3, 2)
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

/// The rows of `x` at `index`, where index `x`'s row count reads a row of
/// zeros: how `SetBatch::slots` (padding) and `SetBatch::owners` (a batch
/// without spheres) point past the real rows.
pub(crate) fn rows_or_zero(x: Tensor<2>, index: Tensor<1, Int>) -> Tensor<2> {
    let [_, width] = x.dims();
    let zero = Tensor::<2>::zeros([1, width], &x.device());
    Tensor::cat(vec![x, zero], 0).select(0, index)
}

impl SphereSets {
    /// Sets for a network of `shape` seeing scenes of a `fov_px` field.
    pub fn new(shape: &SetShape, fov_px: [u32; 2]) -> Self {
        Self {
            trap_px: fov_px.map(|v| 0.5 * v as f32),
            scale_px: 0.5 * shape.fov_px[0] as f32,
            motion_unit_px: shape.motion_unit_px,
            max_spheres: shape.max_spheres,
            inputs: shape.inputs,
            frame: shape.frame,
        }
    }

    /// The features of a scene's spheres, nearest first and at most
    /// `max_spheres`, one row of [`SphereInputs::features`] values each:
    /// position and distance, then (with motion) the displacement over
    /// [`SetShape::motion_unit_px`] and 1 for a sphere new to the view (whose
    /// displacement reads 0), then (with goal) the position and the
    /// displacement along and across the heading to the target.
    pub fn features(&self, scene: Scene) -> Vec<Vec<f32>> {
        self.rows(scene, scene.heading())
    }

    /// [`Self::features`] of `scene`, whose heading is `heading`.
    fn rows(&self, scene: Scene, heading: [f32; 2]) -> Vec<Vec<f32>> {
        let turn = |v: [f32; 2]| match self.frame {
            Frame::Stage => v,
            Frame::Goal => to_goal(v, heading),
        };
        let mut rows: Vec<Vec<f32>> = scene
            .centres
            .iter()
            .enumerate()
            .map(|(k, c)| {
                let offset = [
                    (c[0] - self.trap_px[0]) / self.scale_px,
                    (c[1] - self.trap_px[1]) / self.scale_px,
                ];
                let [dx, dy] = turn(offset);
                let mut row = Vec::with_capacity(self.inputs.features());
                row.extend([dx, dy, dx.hypot(dy)]);
                if !self.inputs.has_motion() {
                    return row;
                }
                // The displacement in motion units, along the stage's axes.
                let moved = scene
                    .displacement(k)
                    .map(|d| d.map(|v| v / self.motion_unit_px));
                match moved {
                    Some(m) => {
                        row.extend(turn(m));
                        row.push(0.0);
                    }
                    None => row.extend([0.0, 0.0, 1.0]),
                }
                // Turned from the stage's axes, whatever the frame.
                if self.inputs == SphereInputs::Goal {
                    row.extend(to_goal(offset, heading));
                    row.extend(to_goal(moved.unwrap_or([0.0; 2]), heading));
                }
                row
            })
            .collect();
        if rows.len() > self.max_spheres {
            rows.sort_by(|a, b| a[2].total_cmp(&b[2]));
            rows.truncate(self.max_spheres);
        }
        rows
    }

    /// The padded sets of each scene, on `device`, padded only as far as
    /// the batch's largest set.
    pub fn batch<'a>(
        &self,
        scenes: impl ExactSizeIterator<Item = Scene<'a>>,
        device: &Device,
    ) -> SetBatch {
        self.batch_padded(scenes, 1, device)
    }

    /// As [`Self::batch`], padded to at least `min_len` spheres.
    pub fn batch_padded<'a>(
        &self,
        scenes: impl ExactSizeIterator<Item = Scene<'a>>,
        min_len: usize,
        device: &Device,
    ) -> SetBatch {
        let per_sphere = self.inputs.features();
        let (sets, headings): (Vec<_>, Vec<_>) = scenes
            .map(|s| {
                let heading = s.heading();
                (self.rows(s, heading), heading)
            })
            .unzip();
        let width = sets.iter().map(Vec::len).max().unwrap_or(0).max(min_len);
        let packed = sets.iter().map(Vec::len).sum::<usize>().max(1);
        let mut features = Vec::with_capacity(packed * per_sphere);
        let mut slots = vec![packed as i64; sets.len() * width];
        let mut owners = Vec::with_capacity(packed);
        let mut counts = Vec::with_capacity(sets.len());
        for (b, set) in sets.iter().enumerate() {
            for (k, f) in set.iter().enumerate() {
                slots[b * width + k] = (features.len() / per_sphere) as i64;
                features.extend_from_slice(f);
                owners.push(b as i64);
            }
            counts.push(set.len().max(1) as f32);
        }
        features.resize(packed * per_sphere, 0.0);
        let n = sets.len();
        owners.resize(packed, n as i64);
        SetBatch {
            spheres: Tensor::from_data(TensorData::new(features, [packed, per_sphere]), device),
            slots: Tensor::from_data(TensorData::new(slots, [n * width]), device),
            owners: Tensor::from_data(TensorData::new(owners, [packed]), device),
            counts: Tensor::from_data(TensorData::new(counts, [n, 1]), device),
            width,
            heading: Tensor::from_data(TensorData::new(headings.concat(), [n, 2]), device),
        }
    }
}
