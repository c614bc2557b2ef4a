//! The outer contour of a blob in a mask (Moore-neighbour tracing with
//! Jacob's stopping rule) and the shape it encloses.

/// The eight neighbours, clockwise (y grows downward) from the west.
const NEIGHBOURS: [[i32; 2]; 8] = [
    [-1, 0],
    [-1, -1],
    [0, -1],
    [1, -1],
    [1, 0],
    [1, 1],
    [0, 1],
    [-1, 1],
];

/// A traced contour: the centres of its boundary pixels in order, the first
/// repeated last, and its chain-code length.
#[derive(Clone, Debug, Default)]
pub struct Contour {
    points: Vec<[i32; 2]>,
    length: f64,
}

/// What a contour encloses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shape {
    /// The pixels inside the contour, boundary included (the polygon's area
    /// plus half its boundary pixels plus one, as Pick's theorem gives).
    pub filled_area: f64,
    /// 4π area / length², for the polygon through the boundary pixels.
    pub circularity: f64,
    /// The polygon's centroid, px (pixel (x, y) at (x, y)).
    pub centroid: [f64; 2],
}

/// Traces the outer contour of the 8-connected blob whose first pixel in
/// raster order is `start`, over the non-zero pixels of `mask` (`w` x `h`).
pub fn trace_outer(mask: &[u8], w: usize, h: usize, start: [i32; 2], contour: &mut Contour) {
    let inside = |p: [i32; 2]| {
        p[0] >= 0
            && p[1] >= 0
            && (p[0] as usize) < w
            && (p[1] as usize) < h
            && mask[p[1] as usize * w + p[0] as usize] != 0
    };
    contour.points.clear();
    contour.points.push(start);
    contour.length = 0.0;
    let mut current = start;
    // Nothing lies west of the first pixel in raster order: search from NW.
    let mut from = 1;
    let mut first_move = None;
    for _ in 0..4 * (w * h).max(1) {
        let Some(d) = (0..8)
            .map(|k| (from + k) % 8)
            .find(|&d| inside([current[0] + NEIGHBOURS[d][0], current[1] + NEIGHBOURS[d][1]]))
        else {
            return; // a single pixel
        };
        if current == start && first_move == Some(d) {
            return;
        }
        first_move.get_or_insert(d);
        current = [current[0] + NEIGHBOURS[d][0], current[1] + NEIGHBOURS[d][1]];
        contour.points.push(current);
        contour.length += if d % 2 == 0 {
            1.0
        } else {
            std::f64::consts::SQRT_2
        };
        from = (d + 6) % 8;
    }
}

impl Contour {
    /// The boundary pixels, in order.
    #[cfg(test)]
    pub fn points(&self) -> &[[i32; 2]] {
        &self.points
    }

    /// Area, circularity and centroid of the region inside.
    pub fn shape(&self) -> Shape {
        let (mut twice_area, mut cx, mut cy) = (0.0f64, 0.0f64, 0.0f64);
        for pair in self.points.windows(2) {
            let ([x0, y0], [x1, y1]) = (pair[0].map(f64::from), pair[1].map(f64::from));
            let cross = x0 * y1 - x1 * y0;
            twice_area += cross;
            cx += (x0 + x1) * cross;
            cy += (y0 + y1) * cross;
        }
        let area = twice_area.abs() / 2.0;
        let centroid = if twice_area.abs() > 1e-9 {
            [cx / (3.0 * twice_area), cy / (3.0 * twice_area)]
        } else {
            // The closed walk, its repeated first point left out.
            let walk = &self.points[..self.points.len().saturating_sub(1).max(1)];
            let n = walk.len() as f64;
            let sum = |axis: usize| walk.iter().map(|p| f64::from(p[axis])).sum::<f64>();
            [sum(0) / n, sum(1) / n]
        };
        Shape {
            filled_area: area + self.points.len().saturating_sub(1) as f64 / 2.0 + 1.0,
            circularity: if self.length > 0.0 {
                4.0 * std::f64::consts::PI * area / (self.length * self.length)
            } else {
                0.0
            },
            centroid,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mask_of(rows: &[&str]) -> (Vec<u8>, usize, usize) {
        let w = rows[0].len();
        let mask = rows
            .iter()
            .flat_map(|r| r.bytes().map(|b| u8::from(b == b'#')))
            .collect();
        (mask, w, rows.len())
    }

    #[test]
    fn a_square_is_traced_clockwise_once_around() {
        let (mask, w, h) = mask_of(&["....", ".##.", ".##.", "...."]);
        let mut contour = Contour::default();
        trace_outer(&mask, w, h, [1, 1], &mut contour);
        assert_eq!(contour.points(), &[[1, 1], [2, 1], [2, 2], [1, 2], [1, 1]]);
        let shape = contour.shape();
        assert_eq!(shape.filled_area, 4.0);
        assert_eq!(shape.centroid, [1.5, 1.5]);
        assert!((shape.circularity - std::f64::consts::PI / 4.0).abs() < 1e-12);
    }

    #[test]
    fn a_ring_is_traced_around_the_outside_and_its_hole_counts_as_inside() {
        let (mask, w, h) = mask_of(&[
            ".......", "..###..", ".#...#.", ".#...#.", ".#...#.", "..###..", ".......",
        ]);
        let mut contour = Contour::default();
        trace_outer(&mask, w, h, [2, 1], &mut contour);
        let shape = contour.shape();
        assert_eq!(contour.points().len(), 13);
        assert_eq!(shape.centroid, [3.0, 3.0]);
        assert_eq!(shape.filled_area, 21.0);
    }

    #[test]
    fn a_single_pixel_and_a_line_have_no_area_but_a_centre() {
        let mut contour = Contour::default();
        let (mask, w, h) = mask_of(&["...", ".#.", "..."]);
        trace_outer(&mask, w, h, [1, 1], &mut contour);
        assert_eq!(contour.shape().filled_area, 1.0);
        assert_eq!(contour.shape().centroid, [1.0, 1.0]);
        let (mask, w, h) = mask_of(&["#...", ".#..", "..#."]);
        trace_outer(&mask, w, h, [0, 0], &mut contour);
        let shape = contour.shape();
        assert_eq!(shape.centroid, [1.0, 1.0]);
        assert_eq!(shape.circularity, 0.0);
    }
}
