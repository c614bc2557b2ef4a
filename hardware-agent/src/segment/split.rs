//! Splitting a blob of touching or overlapping spheres: weighted k-means
//! over its pixels, seeded by farthest points.

/// Centres (binned px) of `k` spheres in the blob made of the pixels
/// `members` (indices into rows of `w`), weighted by |`deviation`|.
pub fn split(members: &[u32], w: usize, deviation: &[f32], k: usize) -> Vec<[f64; 2]> {
    let points: Vec<([f64; 2], f64)> = members
        .iter()
        .map(|&p| {
            let p = p as usize;
            (
                [(p % w) as f64, (p / w) as f64],
                f64::from(deviation[p].abs()) + 1e-6,
            )
        })
        .collect();
    let distance2 = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2);
    let total: f64 = points.iter().map(|p| p.1).sum();
    let mean = [0, 1].map(|axis| points.iter().map(|p| p.0[axis] * p.1).sum::<f64>() / total);
    let mut centres = vec![mean];
    while centres.len() <= k {
        let farthest = points
            .iter()
            .map(|p| p.0)
            .max_by(|&a, &b| {
                let near = |q| {
                    centres
                        .iter()
                        .map(|&c| distance2(q, c))
                        .fold(f64::INFINITY, f64::min)
                };
                near(a).total_cmp(&near(b))
            })
            .expect("a blob has pixels");
        centres.push(farthest);
    }
    centres.remove(0);
    for _ in 0..20 {
        let mut sums = vec![[0.0f64; 3]; k];
        for &(q, weight) in &points {
            let nearest = (0..k)
                .min_by(|&a, &b| distance2(q, centres[a]).total_cmp(&distance2(q, centres[b])))
                .expect("k ≥ 1");
            sums[nearest][0] += weight * q[0];
            sums[nearest][1] += weight * q[1];
            sums[nearest][2] += weight;
        }
        let moved: Vec<[f64; 2]> = sums
            .iter()
            .zip(&centres)
            .map(|(s, &c)| {
                if s[2] > 0.0 {
                    [s[0] / s[2], s[1] / s[2]]
                } else {
                    c
                }
            })
            .collect();
        let shift = moved
            .iter()
            .zip(&centres)
            .map(|(&a, &b)| distance2(a, b))
            .fold(0.0, f64::max);
        centres = moved;
        if shift < 1e-6 {
            break;
        }
    }
    centres
}
