//! The image filters segmentation runs, on row-major f32 and u8 buffers:
//! binning, a separable Gaussian blur, a box mean, and erosion and dilation
//! by a square. Every loop runs along rows or across whole rows, so the
//! compiler vectorises it.

/// Sums `bin` x `bin` blocks of `pixels` (rows of `stride`) into `out`
/// (`w` x `h`), as means; a remainder past the last whole block is dropped.
pub fn bin(pixels: &[u16], stride: usize, bin: usize, w: usize, h: usize, out: &mut [f32]) {
    out.fill(0.0);
    let scale = 1.0 / (bin * bin) as f32;
    for y in 0..h * bin {
        let row = &pixels[y * stride..][..w * bin];
        let dst = &mut out[(y / bin) * w..][..w];
        if bin == 1 {
            for (o, &p) in dst.iter_mut().zip(row) {
                *o = f32::from(p);
            }
        } else {
            for (o, block) in dst.iter_mut().zip(row.chunks_exact(bin)) {
                *o += block.iter().map(|&p| f32::from(p)).sum::<f32>() * scale;
            }
        }
    }
}

/// A normalised Gaussian kernel of σ `sigma`, radius ⌈3σ⌉ (the identity for
/// σ below 0.2).
pub fn gaussian_kernel(sigma: f64) -> Vec<f32> {
    if sigma < 0.2 {
        return vec![1.0];
    }
    let radius = (3.0 * sigma).ceil() as i64;
    let weights: Vec<f64> = (-radius..=radius)
        .map(|k| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f64 = weights.iter().sum();
    weights.iter().map(|w| (w / total) as f32).collect()
}

/// `src` convolved with `kernel` along rows then columns into `dst`
/// (`tmp` holds the intermediate); edges repeat the edge pixel.
pub fn blur(src: &[f32], tmp: &mut [f32], dst: &mut [f32], w: usize, h: usize, kernel: &[f32]) {
    let r = kernel.len() / 2;
    for (row, out) in src.chunks_exact(w).zip(tmp.chunks_exact_mut(w)) {
        out.fill(0.0);
        if w > 2 * r {
            for (k, &weight) in kernel.iter().enumerate() {
                for (o, &p) in out[r..w - r].iter_mut().zip(&row[k..w - 2 * r + k]) {
                    *o += weight * p;
                }
            }
        }
        for j in (0..r.min(w)).chain(w.saturating_sub(r).max(r.min(w))..w) {
            out[j] = kernel
                .iter()
                .enumerate()
                .map(|(k, &weight)| weight * row[(j + k).saturating_sub(r).min(w - 1)])
                .sum();
        }
    }
    for (i, out) in dst.chunks_exact_mut(w).enumerate() {
        out.fill(0.0);
        for (k, &weight) in kernel.iter().enumerate() {
            let y = (i + k).saturating_sub(r).min(h - 1);
            for (o, &p) in out.iter_mut().zip(&tmp[y * w..][..w]) {
                *o += weight * p;
            }
        }
    }
}

/// The mean of `src` over the (2 `radius` + 1)² window around each pixel,
/// clipped to the image, into `dst` (`tmp` holds the row means).
pub fn box_mean(src: &[f32], tmp: &mut [f32], dst: &mut [f32], w: usize, h: usize, radius: usize) {
    let inverse_counts: Vec<f64> = (0..w)
        .map(|j| 1.0 / ((j + radius + 1).min(w) - j.saturating_sub(radius)) as f64)
        .collect();
    for (row, out) in src.chunks_exact(w).zip(tmp.chunks_exact_mut(w)) {
        let mut sum: f64 = row[..radius.min(w)].iter().map(|&p| f64::from(p)).sum();
        for (j, (o, &inverse)) in out.iter_mut().zip(&inverse_counts).enumerate() {
            if j + radius < w {
                sum += f64::from(row[j + radius]);
            }
            if j > radius {
                sum -= f64::from(row[j - radius - 1]);
            }
            *o = (sum * inverse) as f32;
        }
    }
    let mut column = vec![0.0f64; w];
    let mut rows = 0usize;
    for y in 0..radius.min(h) {
        add_row(&mut column, &tmp[y * w..][..w], 1.0);
        rows += 1;
    }
    for (i, out) in dst.chunks_exact_mut(w).enumerate() {
        if i + radius < h {
            add_row(&mut column, &tmp[(i + radius) * w..][..w], 1.0);
            rows += 1;
        }
        if i > radius {
            add_row(&mut column, &tmp[(i - radius - 1) * w..][..w], -1.0);
            rows -= 1;
        }
        let scale = 1.0 / rows as f64;
        for (o, &c) in out.iter_mut().zip(&column) {
            *o = (c * scale) as f32;
        }
    }
}

fn add_row(column: &mut [f64], row: &[f32], sign: f64) {
    for (c, &p) in column.iter_mut().zip(row) {
        *c += sign * f64::from(p);
    }
}

/// Erosion of a 0/1 mask by a (2 `radius` + 1)² square, in place (pixels
/// outside the image do not erode).
pub fn erode(mask: &mut [u8], tmp: &mut [u8], w: usize, h: usize, radius: usize) {
    morph(mask, tmp, w, h, radius, |a, b| a & b);
}

/// Dilation of a 0/1 mask by a (2 `radius` + 1)² square, in place.
pub fn dilate(mask: &mut [u8], tmp: &mut [u8], w: usize, h: usize, radius: usize) {
    morph(mask, tmp, w, h, radius, |a, b| a | b);
}

fn morph(
    mask: &mut [u8],
    tmp: &mut [u8],
    w: usize,
    h: usize,
    radius: usize,
    op: impl Fn(u8, u8) -> u8 + Copy,
) {
    if radius == 0 {
        return;
    }
    for (row, out) in mask.chunks_exact(w).zip(tmp.chunks_exact_mut(w)) {
        out.copy_from_slice(row);
        for shift in 1..=radius.min(w - 1) {
            for (o, &p) in out[..w - shift].iter_mut().zip(&row[shift..]) {
                *o = op(*o, p);
            }
            for (o, &p) in out[shift..].iter_mut().zip(&row[..w - shift]) {
                *o = op(*o, p);
            }
        }
    }
    for i in 0..h {
        let out = &mut mask[i * w..][..w];
        out.copy_from_slice(&tmp[i * w..][..w]);
        for y in i.saturating_sub(radius)..=(i + radius).min(h - 1) {
            if y != i {
                for (o, &p) in out.iter_mut().zip(&tmp[y * w..][..w]) {
                    *o = op(*o, p);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_blur_keeps_a_constant_image_and_spreads_a_point_symmetrically() {
        let (w, h) = (17, 11);
        let kernel = gaussian_kernel(1.5);
        let (mut tmp, mut out) = (vec![0.0; w * h], vec![0.0; w * h]);
        blur(&vec![3.0; w * h], &mut tmp, &mut out, w, h, &kernel);
        assert!(out.iter().all(|&v| (v - 3.0).abs() < 1e-5));
        let mut point = vec![0.0; w * h];
        point[5 * w + 8] = 1.0;
        blur(&point, &mut tmp, &mut out, w, h, &kernel);
        assert!((out.iter().sum::<f32>() - 1.0).abs() < 1e-5);
        assert!((out[5 * w + 6] - out[5 * w + 10]).abs() < 1e-7);
        assert!((out[3 * w + 8] - out[7 * w + 8]).abs() < 1e-7);
    }

    #[test]
    fn a_box_mean_is_the_plain_mean_of_the_clipped_window() {
        let (w, h, r) = (9, 7, 2);
        let src: Vec<f32> = (0..w * h).map(|k| ((k * 37) % 11) as f32).collect();
        let (mut tmp, mut out) = (vec![0.0; w * h], vec![0.0; w * h]);
        box_mean(&src, &mut tmp, &mut out, w, h, r);
        for i in 0..h {
            for j in 0..w {
                let (mut sum, mut n) = (0.0, 0.0);
                for y in i.saturating_sub(r)..=(i + r).min(h - 1) {
                    for x in j.saturating_sub(r)..=(j + r).min(w - 1) {
                        sum += src[y * w + x];
                        n += 1.0;
                    }
                }
                assert!((out[i * w + j] - sum / n).abs() < 1e-4, "({j}, {i})");
            }
        }
    }

    #[test]
    fn opening_removes_specks_and_keeps_squares() {
        let (w, h) = (12, 10);
        let mut mask = vec![0u8; w * h];
        mask[w + 1] = 1;
        for y in 4..8 {
            for x in 5..9 {
                mask[y * w + x] = 1;
            }
        }
        let expected = {
            let mut m = mask.clone();
            m[w + 1] = 0;
            m
        };
        let mut tmp = vec![0u8; w * h];
        erode(&mut mask, &mut tmp, w, h, 1);
        assert_eq!(mask.iter().filter(|&&m| m == 1).count(), 4);
        dilate(&mut mask, &mut tmp, w, h, 1);
        assert_eq!(mask, expected);
    }

    #[test]
    fn binning_averages_blocks_and_drops_the_remainder() {
        let pixels: Vec<u16> = (0..5 * 4).map(|k| k as u16).collect();
        let mut out = vec![0.0; 2 * 2];
        bin(&pixels, 5, 2, 2, 2, &mut out);
        assert_eq!(out, vec![3.0, 5.0, 13.0, 15.0]);
    }
}
