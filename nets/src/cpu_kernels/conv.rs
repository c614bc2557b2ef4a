//! The encoder's convolutions on Burn's CPU backend (flex), forward and
//! backward, each as one matrix product over the whole batch.
//!
//! Burn's own CPU convolution multiplies one image at a time (at 40 × 32
//! the second layer is 32 products of 64 × 512 by 512 × 20) and computes
//! the weight gradient as a convolution with the batch as channels and the
//! output gradient as kernel. Here the batch's patches become one column
//! matrix (im2col, `[in channels × k × k, batch × out pixels]`), and
//!
//! - forward: `y = W · cols + b`,
//! - weight gradient: `dW = dy · colsᵀ`, bias gradient: `db = Σ dy`,
//! - input gradient (when the input needs one): `dcols = Wᵀ · dy`, added
//!   back into the image (col2im),
//!
//! each product one GEMM on Burn's own matrix multiplication (transposes are
//! views, not copies). A column matrix is written whole, over a spare this
//! thread made before where one is free, and where the whole batch fits in
//! one (40 × 32) the backward step reuses the forward step's instead of
//! building it again. Where the input is mostly zeros, as the rendered
//! images are, forward and weight gradient go over its nonzeros instead
//! ([`Nonzeros`]). It is the same convolution: the tests check it against
//! Burn's to 1e-4, forward and gradients. Other devices (wgpu, cuda) keep
//! Burn's convolution.

use super::tensor;
use burn::backend::autodiff::NodeId;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, backend_extension};
use burn::tensor::{Shape, Tensor};
use burn_flex::FlexTensor;
use rayon::prelude::*;
use std::cell::RefCell;
use std::ops::Range;

/// A convolution with square kernels, equal stride and padding on both
/// axes, and a bias: what the encoder's three layers are.
#[backend_extension(Flex, Autodiff)]
pub trait Conv2dKernel: Backend {
    /// `x` `[batch, in, h, w]`, `weight` `[out, in, k, k]`, `bias` `[out]`
    /// → `[batch, out, oh, ow]`.
    fn conv2d(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        stride: usize,
        padding: usize,
    ) -> FloatTensor<Self>;
}

/// The convolution of `x` by `weight` and `bias` (see [`Conv2dKernel`]); only
/// on devices where [`is_cpu_backend`](super::is_cpu_backend) holds.
pub fn conv2d(
    x: Tensor<4>,
    weight: Tensor<4>,
    bias: Tensor<1>,
    stride: usize,
    padding: usize,
) -> Tensor<4> {
    Tensor::from_dispatch(<Dispatch as Conv2dKernel>::conv2d(
        x.into_dispatch(),
        weight.into_dispatch(),
        bias.into_dispatch(),
        stride,
        padding,
    ))
}

impl Conv2dKernel for Flex {
    fn conv2d(
        x: FlexTensor,
        weight: FlexTensor,
        bias: FlexTensor,
        stride: usize,
        padding: usize,
    ) -> FlexTensor {
        forward(
            &x,
            &weight,
            &bias,
            Geometry::of(&x, &weight, stride, padding),
        )
        .0
    }
}

/// The backward step: which inputs need gradients is known only then.
#[derive(Debug)]
struct Conv2dBackward;

impl Backward<Flex, 3> for Conv2dBackward {
    /// The checkpointed input and weight, stride and padding, and the
    /// forward step's column matrix of the whole batch if it kept one.
    type State = (NodeId, NodeId, usize, usize, Option<FlexTensor>);

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, cp: &mut Checkpointer) {
        let [node_x, node_weight, node_bias] = ops.parents;
        let grad: FlexTensor = grads.consume::<Flex>(&ops.node);
        let (x, weight, stride, padding, whole) = ops.state;
        let x: FlexTensor = cp.retrieve_node_output(x);
        let weight: FlexTensor = cp.retrieve_node_output(weight);
        let geometry = Geometry::of(&x, &weight, stride, padding);
        let g = backward(&x, &weight, &grad, geometry, node_x.is_some(), whole);
        if let (Some(node), Some(dx)) = (node_x, g.x) {
            grads.register::<Flex>(node.id, dx);
        }
        if let Some(node) = node_weight {
            grads.register::<Flex>(node.id, g.weight);
        }
        if let Some(node) = node_bias {
            grads.register::<Flex>(node.id, g.bias);
        }
    }
}

impl<C: CheckpointStrategy> Conv2dKernel for Autodiff<Flex, C> {
    fn conv2d(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        stride: usize,
        padding: usize,
    ) -> FloatTensor<Self> {
        let nodes = [x.node(), weight.node(), bias.node()];
        let convolve =
            |x: FloatTensor<Self>, weight: FloatTensor<Self>, bias: FloatTensor<Self>| {
                let (x, weight) = (x.into_primitive(), weight.into_primitive());
                let geometry = Geometry::of(&x, &weight, stride, padding);
                forward(&x, &weight, &bias.into_primitive(), geometry)
            };
        match Conv2dBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(mut prep) => {
                let (x_id, weight_id) = (prep.checkpoint(&x), prep.checkpoint(&weight));
                let (y, whole) = convolve(x, weight, bias);
                prep.finish((x_id, weight_id, stride, padding, whole), y)
            }
            OpsKind::UnTracked(prep) => prep.finish(convolve(x, weight, bias).0),
        }
    }
}

/// Sizes of one convolution.
#[derive(Clone, Copy, Debug)]
struct Geometry {
    batch: usize,
    channels_in: usize,
    height: usize,
    width: usize,
    channels_out: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
    out_height: usize,
    out_width: usize,
}

impl Geometry {
    fn of(x: &FlexTensor, weight: &FlexTensor, stride: usize, padding: usize) -> Self {
        let xs = x.layout().shape();
        let ws = weight.layout().shape();
        assert!(
            xs.num_dims() == 4 && ws.num_dims() == 4 && xs[1] == ws[1] && ws[2] == ws[3],
            "conv2d: input {xs:?} and weight {ws:?} do not fit"
        );
        let out = |size: usize| (size + 2 * padding - ws[2]) / stride + 1;
        Self {
            batch: xs[0],
            channels_in: xs[1],
            height: xs[2],
            width: xs[3],
            channels_out: ws[0],
            kernel: ws[2],
            stride,
            padding,
            out_height: out(xs[2]),
            out_width: out(xs[3]),
        }
    }

    /// Rows of the column matrix: in channels × kernel².
    fn patch(&self) -> usize {
        self.channels_in * self.kernel * self.kernel
    }

    /// Output pixels of one image.
    fn out_pixels(&self) -> usize {
        self.out_height * self.out_width
    }

    /// Whether the output has the input's size, one output pixel per input
    /// pixel (stride 1, padding (kernel − 1) / 2): the encoder's third
    /// layer.
    fn keeps_size(&self) -> bool {
        self.out_height == self.height && self.out_width == self.width && self.stride == 1
    }

    /// Images per column matrix: enough for a product of ~2,000 columns (the
    /// whole batch at 40 × 32), one at a time where an image alone has
    /// more (320 × 256), so that the matrix stays a few megabytes.
    fn chunk(&self) -> usize {
        (2048 / self.out_pixels()).clamp(1, self.batch)
    }

    /// The output rows (or columns) `o` of `outs` whose input row `o ·
    /// stride + k − padding` lies inside `0..size`.
    fn inside(&self, k: usize, size: usize, outs: usize) -> Range<usize> {
        let first = self.padding.saturating_sub(k).div_ceil(self.stride);
        let end = (size + self.padding)
            .checked_sub(k + 1)
            .map_or(0, |last| last / self.stride + 1)
            .min(outs);
        first.min(end)..end
    }
}

thread_local! {
    /// Column matrices this thread made, kept for reuse: a TD3 update
    /// builds dozens of the same few shapes.
    static SPARE_COLUMNS: RefCell<Vec<FlexTensor>> = const { RefCell::new(Vec::new()) };
}

/// Column matrices kept per thread (two shapes per encoder, in forward and
/// backward passes of several networks).
const SPARES: usize = 8;

/// The images `images` of `x` (`[batch, in, h, w]`) as a column matrix
/// `[patch, images × out pixels]`: row (c, ky, kx), column (image, oy, ox)
/// holds `x[image, c, oy·s + ky − p, ox·s + kx − p]`, zero outside. It is
/// written over a matrix of the same shape that this thread made before
/// and nothing holds any more where there is one, instead of a fresh one.
fn column_matrix(x: &[f32], g: Geometry, taps: &[Tap], images: Range<usize>) -> FlexTensor {
    let shape = [g.patch(), images.len() * g.out_pixels()];
    let mut cols = SPARE_COLUMNS
        .with_borrow_mut(|spare| {
            let free = spare.iter_mut().position(|cols| {
                cols.layout().shape().dims::<2>() == shape
                    && cols.try_storage_mut::<f32>().is_some()
            })?;
            Some(spare.swap_remove(free))
        })
        .unwrap_or_else(|| tensor(vec![0f32; shape.iter().product()], shape));
    im2col(cols.storage_mut(), x, g, taps, images);
    SPARE_COLUMNS.with_borrow_mut(|spare| {
        if spare.len() == SPARES {
            spare.remove(0);
        }
        spare.push(cols.clone());
    });
    cols
}

/// Writes the column matrix of `images` (see [`column_matrix`]) into `cols`,
/// every element of it.
fn im2col(cols: &mut [f32], x: &[f32], g: Geometry, taps: &[Tap], images: Range<usize>) {
    let (k, plane, n) = (g.kernel, g.height * g.width, g.out_pixels());
    let columns = images.len() * n;
    cols.par_chunks_mut(columns)
        .enumerate()
        .for_each(|(row, col)| {
            let (c, ky, kx) = (row / (k * k), row / k % k, row % k);
            let tap = &taps[row % (k * k)];
            for (image, out) in images.clone().zip(col.chunks_exact_mut(n)) {
                let channel = &x[(image * g.channels_in + c) * plane..][..plane];
                if g.keeps_size() {
                    if !tap.covers(g) {
                        out.fill(0.0);
                    }
                    // Output row oy is input row oy + ky − p shifted by kx −
                    // p: the rows ys are one block of the plane, shifted,
                    // whose columns outside xs are then zeroed again.
                    let (ys, xs) = (tap.ys.clone(), tap.xs.clone());
                    if ys.is_empty() || xs.is_empty() {
                        // A tap that reads only padding (maps narrower
                        // than the kernel's reach).
                        continue;
                    }
                    let shift = (ky * g.width + kx) as isize - (g.padding * (g.width + 1)) as isize;
                    let (start, end) = (ys.start * g.width, ys.end * g.width);
                    let skip = (-(start as isize + shift)).max(0) as usize;
                    let cut = (end as isize + shift - plane as isize).max(0) as usize;
                    let from = (start + skip).saturating_add_signed(shift);
                    out[start + skip..end - cut]
                        .copy_from_slice(&channel[from..][..end - cut - start - skip]);
                    for line in out[start..end].chunks_exact_mut(g.width) {
                        line[..xs.start].fill(0.0);
                        line[xs.end..].fill(0.0);
                    }
                    continue;
                }
                for (v, &source) in out.iter_mut().zip(&tap.sources) {
                    *v = channel.get(source as usize).copied().unwrap_or(0.0);
                }
            }
        });
}

/// Where one kernel tap (ky, kx) reads: the output rows `ys` and columns
/// `xs` whose input pixel lies inside the image, and that input pixel's
/// index in its plane for the first of them; and, unless the convolution
/// keeps the size, each output pixel's input index (`u32::MAX` in the
/// padding).
struct Tap {
    ys: Range<usize>,
    xs: Range<usize>,
    first: usize,
    sources: Vec<u32>,
}

impl Tap {
    /// Every tap of `g`'s kernel, row by row.
    fn all(g: Geometry) -> Vec<Tap> {
        let k = g.kernel;
        (0..k * k)
            .map(|tap| {
                let (ky, kx) = (tap / k, tap % k);
                let (ys, xs) = (
                    g.inside(ky, g.height, g.out_height),
                    g.inside(kx, g.width, g.out_width),
                );
                let first = (ys.start * g.stride + ky).saturating_sub(g.padding) * g.width
                    + (xs.start * g.stride + kx).saturating_sub(g.padding);
                let mut sources = Vec::new();
                if !g.keeps_size() {
                    sources = vec![u32::MAX; g.out_pixels()];
                    for (oy, row) in ys.clone().zip((first..).step_by(g.stride * g.width)) {
                        let line = &mut sources[oy * g.out_width..][xs.clone()];
                        for (source, x) in line.iter_mut().zip((row..).step_by(g.stride)) {
                            *source = x as u32;
                        }
                    }
                }
                Tap {
                    ys,
                    xs,
                    first,
                    sources,
                }
            })
            .collect()
    }

    /// Whether every output pixel's input lies inside the image.
    fn covers(&self, g: Geometry) -> bool {
        self.ys.len() == g.out_height && self.xs.len() == g.out_width
    }
}

/// Adds the gradient of a column matrix of `images` back into those
/// images' planes of `dx` (`[batch, in, h, w]`): the transpose of
/// [`im2col`].
fn col2im(dx: &mut [f32], dcols: &[f32], g: Geometry, taps: &[Tap], images: Range<usize>) {
    let (k, plane, n) = (g.kernel, g.height * g.width, g.out_pixels());
    let columns = images.len() * n;
    let planes = &mut dx[images.start * g.channels_in * plane..images.end * g.channels_in * plane];
    planes
        .par_chunks_mut(plane)
        .enumerate()
        .for_each(|(index, channel)| {
            let (image, c) = (index / g.channels_in, index % g.channels_in);
            for (tap, t) in taps.iter().enumerate() {
                let d = &dcols[(c * k * k + tap) * columns + image * n..][..n];
                for (oy, first) in t.ys.clone().zip((t.first..).step_by(g.stride * g.width)) {
                    let d = &d[oy * g.out_width..][t.xs.clone()];
                    if g.stride == 1 {
                        for (v, d) in channel[first..][..d.len()].iter_mut().zip(d) {
                            *v += d;
                        }
                    } else {
                        for (v, d) in channel[first..].iter_mut().step_by(g.stride).zip(d) {
                            *v += d;
                        }
                    }
                }
            }
        });
}

/// The batch in chunks of [`Geometry::chunk`] images.
fn chunks(g: Geometry) -> impl Iterator<Item = Range<usize>> {
    (0..g.batch)
        .step_by(g.chunk())
        .map(move |start| start..(start + g.chunk()).min(g.batch))
}

/// The nonzero inputs of each image, where few are: an image rendered
/// from sphere centres is mostly zeros, so the first layer is a sum of
/// kernel taps over its lit pixels instead of a product over every patch
/// (the same sums, in another order).
struct Nonzeros(Vec<Vec<(usize, f32)>>);

impl Nonzeros {
    /// At most this share of the input nonzero, or `None`.
    const MAX_DENSITY: usize = 16;

    /// The nonzeros of each image of `x` as (index within the image,
    /// value), if at most 1 in [`Self::MAX_DENSITY`] is; stops counting as
    /// soon as more are.
    fn of(x: &[f32], g: Geometry) -> Option<Self> {
        let size = g.channels_in * g.height * g.width;
        let budget = x.len() / Self::MAX_DENSITY;
        let mut found = 0;
        let mut images = Vec::with_capacity(g.batch);
        for image in x.chunks_exact(size) {
            let mut lit = Vec::new();
            // Runs of 16 tested at once (an or of their bits, sign
            // aside), most of them dark.
            for (run, values) in image.chunks(16).enumerate() {
                if values.iter().fold(0, |a, v| a | (v.to_bits() << 1)) == 0 {
                    continue;
                }
                for (i, &v) in values.iter().enumerate() {
                    if v != 0.0 {
                        found += 1;
                        if found > budget {
                            return None;
                        }
                        lit.push((run * 16 + i, v));
                    }
                }
            }
            images.push(lit);
        }
        Some(Self(images))
    }

    /// Calls `f(output pixel, kernel row (c, ky, kx))` for every output
    /// pixel whose patch holds input `index` of an image.
    fn taps(index: usize, g: Geometry, mut f: impl FnMut(usize, usize)) {
        let plane = g.height * g.width;
        let (c, iy, ix) = (index / plane, index % plane / g.width, index % g.width);
        // Outputs o with o·s + k − p = i for some 0 ≤ k < kernel.
        let outs = |i: usize, outs: usize| {
            let first = (i + g.padding + 1)
                .saturating_sub(g.kernel)
                .div_ceil(g.stride);
            let end = ((i + g.padding) / g.stride + 1).min(outs);
            first..end.max(first)
        };
        for oy in outs(iy, g.out_height) {
            let ky = iy + g.padding - oy * g.stride;
            for ox in outs(ix, g.out_width) {
                let kx = ix + g.padding - ox * g.stride;
                f(oy * g.out_width + ox, (c * g.kernel + ky) * g.kernel + kx);
            }
        }
    }

    /// The convolution: bias plus each nonzero input times its taps.
    fn forward(&self, weight: &FlexTensor, bias: &[f32], g: Geometry) -> FlexTensor {
        // Weights as [patch row, out channel], so that one tap adds a
        // contiguous run of out channels to an output pixel.
        let w = weight.storage::<f32>();
        let co = g.channels_out;
        let mut taps = vec![0f32; g.patch() * co];
        for (row, dst) in taps.chunks_exact_mut(co).enumerate() {
            for (c, t) in dst.iter_mut().enumerate() {
                *t = w[c * g.patch() + row];
            }
        }
        let n = g.out_pixels();
        let mut out = vec![0f32; g.batch * co * n];
        out.par_chunks_mut(co * n)
            .zip(&self.0)
            .for_each(|(image, lit)| {
                let mut acc = vec![0f32; n * co]; // [out pixel, out channel]
                for &(index, v) in lit {
                    Self::taps(index, g, |pixel, row| {
                        let acc = &mut acc[pixel * co..][..co];
                        for (a, t) in acc.iter_mut().zip(&taps[row * co..][..co]) {
                            *a += v * t;
                        }
                    });
                }
                for (c, plane) in image.chunks_exact_mut(n).enumerate() {
                    for (pixel, o) in plane.iter_mut().enumerate() {
                        *o = acc[pixel * co + c] + bias[c];
                    }
                }
            });
        tensor(out, [g.batch, co, g.out_height, g.out_width])
    }

    /// The weight gradient `[out, in, k, k]` from the output gradient `dy`
    /// (`[batch, out, out pixels]`): each nonzero input times the output
    /// gradient of every pixel it feeds.
    fn weight_grad(&self, dy: &[f32], g: Geometry) -> Vec<f32> {
        let (co, n) = (g.channels_out, g.out_pixels());
        let sum = self
            .0
            .par_iter()
            .enumerate()
            .fold(
                || vec![0f32; g.patch() * co], // [patch row, out channel]
                |mut dw, (b, lit)| {
                    // This image's dy as [out pixel, out channel].
                    let image = &dy[b * co * n..][..co * n];
                    let mut dyt = vec![0f32; n * co];
                    for (c, plane) in image.chunks_exact(n).enumerate() {
                        for (pixel, d) in plane.iter().enumerate() {
                            dyt[pixel * co + c] = *d;
                        }
                    }
                    for &(index, v) in lit {
                        Self::taps(index, g, |pixel, row| {
                            let dw = &mut dw[row * co..][..co];
                            for (a, d) in dw.iter_mut().zip(&dyt[pixel * co..][..co]) {
                                *a += v * d;
                            }
                        });
                    }
                    dw
                },
            )
            .reduce(
                || vec![0f32; g.patch() * co],
                |mut a, b| {
                    for (a, b) in a.iter_mut().zip(b) {
                        *a += b;
                    }
                    a
                },
            );
        // [patch row, out channel] → [out channel, patch row].
        let mut dw = vec![0f32; co * g.patch()];
        for (row, src) in sum.chunks_exact(co).enumerate() {
            for (c, d) in src.iter().enumerate() {
                dw[c * g.patch() + row] = *d;
            }
        }
        dw
    }
}

/// The convolution, and the column matrix of the whole batch where it was
/// made in one piece (see [`Geometry::chunk`]), for the backward step.
fn forward(
    x: &FlexTensor,
    weight: &FlexTensor,
    bias: &FlexTensor,
    g: Geometry,
) -> (FlexTensor, Option<FlexTensor>) {
    let x = x.to_contiguous();
    let bias = bias.to_contiguous();
    let bias = bias.storage::<f32>();
    if let Some(nonzeros) = Nonzeros::of(x.storage(), g) {
        return (nonzeros.forward(&weight.to_contiguous(), bias, g), None);
    }
    let weight = weight.reshape(Shape::from([g.channels_out, g.patch()]));
    let n = g.out_pixels();
    let mut out = vec![0f32; g.batch * g.channels_out * n];
    let (taps, mut whole) = (Tap::all(g), None);
    for images in chunks(g) {
        // [out, images × out pixels] → [images, out, out pixels], plus the
        // bias.
        let cols = column_matrix(x.storage(), g, &taps, images.clone());
        if images.len() == g.batch {
            whole = Some(cols.clone());
        }
        let y = burn_flex::ops::matmul::matmul(weight.clone(), cols);
        let y = y.storage::<f32>();
        let columns = images.len() * n;
        out[images.start * g.channels_out * n..images.end * g.channels_out * n]
            .par_chunks_mut(n)
            .enumerate()
            .for_each(|(index, plane)| {
                let (image, c) = (index / g.channels_out, index % g.channels_out);
                let src = &y[c * columns + image * n..][..n];
                for (o, s) in plane.iter_mut().zip(src) {
                    *o = s + bias[c];
                }
            });
    }
    (
        tensor(out, [g.batch, g.channels_out, g.out_height, g.out_width]),
        whole,
    )
}

/// The gradients of one convolution.
struct Grads {
    x: Option<FlexTensor>,
    weight: FlexTensor,
    bias: FlexTensor,
}

/// The gradients from the output gradient `grad`; `whole` is the forward
/// step's column matrix of the whole batch, if it kept one.
fn backward(
    x: &FlexTensor,
    weight: &FlexTensor,
    grad: &FlexTensor,
    g: Geometry,
    input_grad: bool,
    mut whole: Option<FlexTensor>,
) -> Grads {
    let (x, grad) = (x.to_contiguous(), grad.to_contiguous());
    let dy = grad.storage::<f32>();
    let weight_t = weight
        .reshape(Shape::from([g.channels_out, g.patch()]))
        .transpose(0, 1);
    let n = g.out_pixels();
    let mut dbias = vec![0f32; g.channels_out];
    if !input_grad && let Some(nonzeros) = Nonzeros::of(x.storage(), g) {
        for (c, db) in dbias.iter_mut().enumerate() {
            *db = (0..g.batch)
                .map(|b| dy[(b * g.channels_out + c) * n..][..n].iter().sum::<f32>())
                .sum();
        }
        return Grads {
            x: None,
            weight: tensor(
                nonzeros.weight_grad(dy, g),
                [g.channels_out, g.channels_in, g.kernel, g.kernel],
            ),
            bias: tensor(dbias, [g.channels_out]),
        };
    }
    let mut dweight = vec![0f32; g.channels_out * g.patch()];
    let mut dx = input_grad.then(|| vec![0f32; g.batch * g.channels_in * g.height * g.width]);
    let taps = Tap::all(g);
    for images in chunks(g) {
        // dy of these images `[images, out, out pixels]` → `[out, images ×
        // out pixels]`.
        let columns = images.len() * n;
        let mut dyt = vec![0f32; g.channels_out * columns];
        dyt.par_chunks_mut(columns)
            .enumerate()
            .for_each(|(c, row)| {
                for (image, dst) in images.clone().zip(row.chunks_exact_mut(n)) {
                    dst.copy_from_slice(&dy[(image * g.channels_out + c) * n..][..n]);
                }
            });
        for (db, row) in dbias.iter_mut().zip(dyt.chunks_exact(columns)) {
            *db += row.iter().sum::<f32>();
        }
        let dyt = tensor(dyt, [g.channels_out, columns]);
        let cols = match whole.take() {
            Some(cols) if images.len() == g.batch => cols,
            _ => column_matrix(x.storage(), g, &taps, images.clone()),
        };
        let dw = burn_flex::ops::matmul::matmul(dyt.clone(), cols.transpose(0, 1));
        for (a, d) in dweight.iter_mut().zip(dw.storage::<f32>()) {
            *a += d;
        }
        if let Some(dx) = dx.as_mut() {
            let dcols = burn_flex::ops::matmul::matmul(weight_t.clone(), dyt);
            col2im(dx, dcols.storage(), g, &taps, images);
        }
    }
    Grads {
        x: dx.map(|dx| tensor(dx, [g.batch, g.channels_in, g.height, g.width])),
        weight: tensor(dweight, [g.channels_out, g.channels_in, g.kernel, g.kernel]),
        bias: tensor(dbias, [g.channels_out]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::Param;
    use burn::nn::PaddingConfig2d;
    use burn::nn::conv::Conv2dConfig;
    use burn::tensor::{Device, Distribution};

    /// The input a test convolves.
    #[derive(Clone, Copy)]
    enum Input {
        /// Normal noise, with a gradient.
        Dense,
        /// A 0/1 image with about 1 in 50 pixels lit (the sparse path), and
        /// a gradient or not.
        Sparse { grad: bool },
    }

    /// Burn's convolution and this one on the same random input and
    /// weights: outputs, and the gradients of a random linear function of
    /// the output, to 1e-4.
    fn check(
        input: Input,
        batch: usize,
        channels: [usize; 2],
        size: [usize; 2],
        kernel: usize,
        stride: usize,
        padding: usize,
    ) {
        let device = Device::flex().autodiff();
        device.seed(11);
        let conv = Conv2dConfig::new(channels, [kernel, kernel])
            .with_stride([stride, stride])
            .with_padding(PaddingConfig2d::Explicit(
                padding, padding, padding, padding,
            ))
            .init(&device);
        let shape = [batch, channels[0], size[0], size[1]];
        let x = match input {
            Input::Dense => Tensor::<4>::random(shape, Distribution::Normal(0.0, 1.0), &device),
            Input::Sparse { .. } => {
                Tensor::<4>::random(shape, Distribution::Uniform(0.0, 1.0), &device)
                    .lower_elem(0.02)
                    .float()
            }
        };
        if let Input::Sparse { .. } = input {
            let values = x.clone().into_data().try_to_vec::<f32>().unwrap();
            let lit = values.iter().filter(|v| **v != 0.0).count();
            assert!(lit * Nonzeros::MAX_DENSITY <= values.len(), "not sparse");
        }
        let grad_x = !matches!(input, Input::Sparse { grad: false });
        let out = |s: usize| (s + 2 * padding - kernel) / stride + 1;
        let probe = Tensor::<4>::random(
            [batch, channels[1], out(size[0]), out(size[1])],
            Distribution::Normal(0.0, 1.0),
            &device,
        )
        .detach();
        let run = |fast: bool| {
            let x = match grad_x {
                true => Param::from_tensor(x.clone().detach()).val(),
                false => x.clone().detach(),
            };
            let weight = conv.weight.val();
            let bias = conv.bias.as_ref().expect("bias").val();
            let y = if fast {
                conv2d(x.clone(), weight.clone(), bias.clone(), stride, padding)
            } else {
                conv.forward(x.clone())
            };
            let grads = (y.clone() * probe.clone()).sum().backward();
            let grad = |t: &Tensor<4>| t.grad(&grads).map(|g| g.into_data());
            (
                y.into_data(),
                grad(&x),
                grad(&weight).expect("weight gradient"),
                bias.grad(&grads).expect("bias gradient").into_data(),
            )
        };
        let plain = run(false);
        let fast = run(true);
        // 1e-4 of the value, or absolutely where it is near zero: sums of
        // thousands of terms in another order differ in the last bits.
        let tolerance = burn::tensor::Tolerance::rel_abs(1e-4, 1e-4);
        fast.0.assert_approx_eq::<f32>(&plain.0, tolerance);
        assert_eq!(fast.1.is_some(), grad_x);
        if let (Some(fast), Some(plain)) = (&fast.1, &plain.1) {
            fast.assert_approx_eq::<f32>(plain, tolerance);
        }
        fast.2.assert_approx_eq::<f32>(&plain.2, tolerance);
        fast.3.assert_approx_eq::<f32>(&plain.3, tolerance);
    }

    #[test]
    fn each_layer_of_the_encoder_matches_burns_convolution() {
        check(Input::Dense, 3, [1, 32], [32, 40], 8, 4, 2);
        check(Input::Dense, 3, [32, 64], [8, 10], 4, 2, 1);
        check(Input::Dense, 3, [64, 64], [4, 5], 3, 1, 1);
        check(Input::Dense, 2, [1, 32], [37, 29], 8, 4, 2);
    }

    #[test]
    fn feature_maps_one_pixel_wide_or_high_match_too() {
        // The paper's layers at the smallest images of the field's aspect
        // (10 x 8 and 15 x 12): the second and third layers' maps are 1 x 1.
        for size in [[8, 10], [12, 15]] {
            check(Input::Dense, 3, [1, 32], size, 8, 4, 2);
            check(Input::Sparse { grad: false }, 3, [1, 32], size, 8, 4, 2);
        }
        check(Input::Dense, 3, [32, 64], [2, 2], 4, 2, 1);
        check(Input::Dense, 3, [32, 64], [3, 3], 4, 2, 1);
        check(Input::Dense, 3, [64, 64], [1, 1], 3, 1, 1);
        // One row or one column only.
        check(Input::Dense, 2, [4, 8], [1, 5], 3, 1, 1);
        check(Input::Dense, 2, [4, 8], [6, 1], 3, 1, 1);
        check(Input::Dense, 2, [4, 8], [2, 7], 4, 2, 1);
    }

    #[test]
    fn batches_split_into_chunks_match_too() {
        // 100 output pixels an image: chunks of 20, 20 and 5 images.
        check(Input::Dense, 45, [3, 5], [10, 10], 3, 1, 1);
        // 1,600: one image at a time.
        check(Input::Dense, 4, [2, 3], [40, 40], 3, 1, 1);
        // Strided with padding, 400: chunks of 5, 5 and 2 images, the
        // second refilling the first's matrix.
        check(Input::Dense, 12, [2, 3], [40, 40], 4, 2, 1);
    }

    #[test]
    fn a_column_matrix_reused_from_a_spare_is_written_everywhere() {
        // Spares of the shapes the second and third layers' column
        // matrices take at 8 × 10 in batches of 3, full of NaN: every
        // element the convolutions read must be written over, padding
        // included.
        for shape in [[32 * 4 * 4, 3 * 4 * 5], [64 * 3 * 3, 3 * 4 * 5]] {
            let poison = vec![f32::NAN; shape[0] * shape[1]];
            SPARE_COLUMNS.with_borrow_mut(|spare| spare.push(tensor(poison, shape)));
        }
        check(Input::Dense, 3, [32, 64], [8, 10], 4, 2, 1);
        check(Input::Dense, 3, [64, 64], [4, 5], 3, 1, 1);
    }

    #[test]
    fn mostly_zero_images_match_by_their_lit_pixels() {
        for grad in [false, true] {
            let input = Input::Sparse { grad };
            check(input, 4, [1, 32], [32, 40], 8, 4, 2);
            check(input, 3, [1, 32], [61, 83], 8, 4, 2);
            check(input, 3, [2, 5], [9, 7], 3, 2, 1);
        }
    }
}
