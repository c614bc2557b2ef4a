//! Sphere centres → binary image, by `docs/spec.md` §2's exact pixel rule.
//!
//! Image pixel (column j, row i) covers full-resolution
//! [s·j, s·j + s) x [s·i, s·i + s); it is on iff its centre
//! (s·(j + 0.5), s·(i + 0.5)) lies within the sphere radius (inclusive) of
//! some sphere centre. A disc is drawn as one run of pixels per row: the run's
//! ends come from a square root and are then settled by the rule itself, so
//! the result is the rule's, bit for bit, at any resolution.

use crate::config::{EnvConfig, ImageConfig};
use crate::num;
use tweezer_config::ConfigError;

/// A pixel type a binary image can be written in.
pub trait Pixel: Copy + Send + Sync + 'static {
    /// Value of a pixel covered by a sphere.
    const ON: Self;
    /// Value of an empty pixel.
    const OFF: Self;

    /// Sets `out[a..b]` to `value` (`a < b <= out.len()`).
    #[inline]
    fn fill_run(out: &mut [Self], a: usize, b: usize, value: Self) {
        out[a..b].fill(value);
    }
}

impl Pixel for u8 {
    const ON: Self = 1;
    const OFF: Self = 0;

    /// Runs of up to 16 pixels (every run at the paper's resolution) are
    /// written as one 16-byte blend instead of a call to `memset`.
    #[inline]
    fn fill_run(out: &mut [u8], a: usize, b: usize, value: u8) {
        let n = b - a;
        if (1..=16).contains(&n)
            && let Some(chunk) = out.get_mut(a..a + 16)
        {
            let chunk: &mut [u8; 16] = chunk.try_into().expect("16 bytes");
            let mask = u128::MAX >> (128 - 8 * n);
            let fill = u128::from_le_bytes([value; 16]);
            let old = u128::from_le_bytes(*chunk);
            *chunk = ((old & !mask) | (fill & mask)).to_le_bytes();
            return;
        }
        out[a..b].fill(value);
    }
}

impl Pixel for f32 {
    const ON: Self = 1.0;
    const OFF: Self = 0.0;
}

/// An output slice whose length is not the image's.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("render target holds {got} pixels, but a {width}x{height} image needs {expected}")]
pub struct SizeMismatch {
    /// Length given.
    pub got: usize,
    /// Length needed.
    pub expected: usize,
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
}

/// Renders sphere centres (full-resolution FOV px) into row-major images of a
/// fixed resolution. Shared by every process that shows a network an image.
#[derive(Clone, Debug, PartialEq)]
pub struct Renderer {
    width: usize,
    height: usize,
    /// Full-resolution px per image pixel (the shrink factor s).
    scale: f64,
    radius: f64,
    /// The runs of the trapped sphere, at the FOV centre, drawn in every image.
    trap_runs: Vec<Run>,
    /// `columns[j + pad]`: full-resolution x of the centre of column `j`,
    /// for every column a disc that touches the image can reach.
    columns: Vec<f64>,
    pad: i64,
}

/// Full-resolution coordinate of the centre of image pixel `j` along an
/// axis: s·(j + 0.5). Every use computes it by this one expression, so the
/// table and the rule agree to the bit.
#[inline]
fn pixel_centre(scale: f64, j: i64) -> f64 {
    scale * (j as f64 + 0.5)
}

/// One run of lit pixels: `start..end` in row-major pixel indices.
type Run = (usize, usize);

impl Renderer {
    /// A renderer for a field of view of `fov_px` shown at `image`
    /// resolution, spheres of `radius` px, and the trapped sphere at the FOV
    /// centre.
    pub fn new(fov_px: [u32; 2], image: ImageConfig, radius: f64) -> Result<Self, ConfigError> {
        image.validate(fov_px)?;
        if !(radius.is_finite() && radius > 0.0) {
            return Err(ConfigError::Invalid {
                field: "sphere_diameter_px".into(),
                reason: format!("radius must be finite and > 0, got {radius}"),
            });
        }
        let scale = f64::from(fov_px[0]) / f64::from(image.width);
        let pad = (2.0 * radius / scale).ceil() as i64 + 3;
        let width = i64::from(image.width);
        let mut renderer = Self {
            width: image.width as usize,
            height: image.height as usize,
            scale,
            radius,
            trap_runs: Vec::new(),
            columns: (-pad..width + pad)
                .map(|j| pixel_centre(scale, j))
                .collect(),
            pad,
        };
        let trap = [0.5 * f64::from(fov_px[0]), 0.5 * f64::from(fov_px[1])];
        let mut trap_runs = Vec::new();
        renderer.runs(trap, |run| trap_runs.push(run));
        renderer.trap_runs = trap_runs;
        Ok(renderer)
    }

    /// The renderer of an environment configuration.
    pub fn for_config(config: &EnvConfig) -> Result<Self, ConfigError> {
        Self::new(config.fov_px, config.image, config.sphere_radius_px())
    }

    /// The same renderer without the trapped sphere (for pictures of free
    /// spheres only, or a trap drawn elsewhere).
    pub fn without_trap(mut self) -> Self {
        self.trap_runs.clear();
        self
    }

    /// Image width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Pixels in one image.
    pub fn pixels(&self) -> usize {
        self.width * self.height
    }

    /// Whether image pixel (j, i) is covered by a sphere at `centre`: the
    /// rule of `docs/spec.md` §2 itself.
    #[inline]
    pub fn covers(&self, centre: [f64; 2], j: i64, i: i64) -> bool {
        let dx = pixel_centre(self.scale, j) - centre[0];
        let dy = pixel_centre(self.scale, i) - centre[1];
        dx * dx + dy * dy <= self.radius * self.radius
    }

    /// Calls `emit` with the run of pixels the disc at `centre` lights in
    /// each image row it touches.
    ///
    /// The row holding the centre has the widest run, and runs shrink row by
    /// row away from it, so the widest run is found once (a square root for
    /// an estimate, then the rule) and every other row's ends are walked
    /// inward from its neighbour's by the rule alone.
    #[inline]
    fn runs(&self, centre: [f64; 2], mut emit: impl FnMut(Run)) {
        let [x, y] = centre;
        let (s, r) = (self.scale, self.radius);
        let inv_s = 1.0 / s;
        // Centres far outside the image light nothing (and could overflow).
        let reach = r + s;
        if !(x > -reach
            && y > -reach
            && x < self.width as f64 * s + reach
            && y < self.height as f64 * s + reach)
        {
            return;
        }
        let mid = num::floor(y * inv_s);
        let dy = pixel_centre(s, mid) - y;
        let rest = r * r - dy * dy;
        if rest < 0.0 {
            return;
        }
        let h = rest.sqrt();
        let mut j0 = num::ceil((x - h) * inv_s - 0.5);
        let mut j1 = num::floor((x + h) * inv_s - 0.5);
        while self.covers(centre, j0 - 1, mid) {
            j0 -= 1;
        }
        while self.covers(centre, j1 + 1, mid) {
            j1 += 1;
        }
        // Every row's run lies within the middle row's: tabulate dx² over it
        // once (the same products `covers` forms, so the same bits).
        let dx2 = |j: i64| {
            let dx = self.columns[(j + self.pad) as usize] - x;
            dx * dx
        };
        let width = (j1 - j0 + 1).max(0) as usize;
        if width <= DX2_TABLE {
            let mut table = [0.0; DX2_TABLE];
            for (k, entry) in table[..width].iter_mut().enumerate() {
                *entry = dx2(j0 + k as i64);
            }
            let lookup = |j: i64| table[(j - j0) as usize];
            self.walk(y, mid, -1, (j0, j1), &lookup, &mut emit);
            self.walk(y, mid + 1, 1, (j0, j1), &lookup, &mut emit);
        } else {
            self.walk(y, mid, -1, (j0, j1), &dx2, &mut emit);
            self.walk(y, mid + 1, 1, (j0, j1), &dx2, &mut emit);
        }
    }

    /// Emits the runs of rows `from`, `from + step`, ... while they are lit
    /// and in the image, each found by shrinking the run before it.
    #[inline]
    fn walk(
        &self,
        y: f64,
        from: i64,
        step: i64,
        run: (i64, i64),
        dx2: &impl Fn(i64) -> f64,
        emit: &mut impl FnMut(Run),
    ) {
        let last_row = self.height as i64 - 1;
        let last_col = self.width as i64 - 1;
        let (s, r2) = (self.scale, self.radius * self.radius);
        let (mut a, mut b) = run;
        let mut i = from;
        while (step < 0 && i >= 0) || (step > 0 && i <= last_row) {
            // `covers`, with the row's term computed once.
            let dy = pixel_centre(s, i) - y;
            let dy2 = dy * dy;
            let inside = |j: i64| dx2(j) + dy2 <= r2;
            while a <= b && !inside(a) {
                a += 1;
            }
            while b >= a && !inside(b) {
                b -= 1;
            }
            if a > b {
                return;
            }
            let (j0, j1) = (a.max(0), b.min(last_col));
            if i <= last_row && i >= 0 && j0 <= j1 {
                let row = i as usize * self.width;
                emit((row + j0 as usize, row + j1 as usize + 1));
            }
            i += step;
        }
    }

    /// Draws the trapped sphere and then `centres`, passing each run to `draw`;
    /// `lit` is told of the free spheres' runs only (the trap's never move).
    #[inline]
    fn draw_all(&self, centres: &[[f32; 2]], mut draw: impl FnMut(Run, bool)) {
        for &run in &self.trap_runs {
            draw(run, false);
        }
        for &[x, y] in centres {
            self.runs([f64::from(x), f64::from(y)], |run| draw(run, true));
        }
    }

    /// Renders the trapped sphere and `centres` into `out` (row-major,
    /// `width * height` pixels), overwriting every pixel. Allocates nothing.
    pub fn render<P: Pixel>(
        &self,
        centres: &[[f32; 2]],
        out: &mut [P],
    ) -> Result<(), SizeMismatch> {
        self.check_len(out.len())?;
        out.fill(P::OFF);
        self.draw_all(centres, |(a, b), _| P::fill_run(out, a, b, P::ON));
        Ok(())
    }

    fn check_len(&self, got: usize) -> Result<(), SizeMismatch> {
        if got == self.pixels() {
            Ok(())
        } else {
            Err(SizeMismatch {
                got,
                expected: self.pixels(),
                width: self.width,
                height: self.height,
            })
        }
    }
}

/// Widest middle run whose dx² are tabulated on the stack (55 columns is a
/// 54 px sphere at full resolution).
const DX2_TABLE: usize = 64;

/// Pixels cleared at once when erasing a short run.
const ERASE_BLOCK: usize = 16;

/// An image kept up to date from one observation to the next: only the
/// pixels of the previous discs are cleared and the new discs drawn, which is
/// exact and costs a few hundred pixel writes instead of a whole image.
#[derive(Clone, Debug)]
pub struct Frame<P: Pixel> {
    pixels: Vec<P>,
    lit: Vec<Run>,
}

impl<P: Pixel> Frame<P> {
    /// A blank frame for `renderer`'s resolution.
    pub fn new(renderer: &Renderer) -> Self {
        Self {
            pixels: vec![P::OFF; renderer.pixels()],
            lit: Vec::new(),
        }
    }

    /// Redraws the frame to show `centres` (and the trapped sphere).
    pub fn update(
        &mut self,
        renderer: &Renderer,
        centres: &[[f32; 2]],
    ) -> Result<(), SizeMismatch> {
        renderer.check_len(self.pixels.len())?;
        // Everything is erased before anything is drawn, so a run may be
        // cleared with the pixels after it: one fixed-size store.
        let len = self.pixels.len();
        for &(a, b) in &self.lit {
            if b - a <= ERASE_BLOCK && a + ERASE_BLOCK <= len {
                self.pixels[a..a + ERASE_BLOCK].fill(P::OFF);
            } else {
                self.pixels[a..b].fill(P::OFF);
            }
        }
        self.lit.clear();
        renderer.draw_all(centres, |(a, b), moves| {
            P::fill_run(&mut self.pixels, a, b, P::ON);
            if moves {
                self.lit.push((a, b));
            }
        });
        Ok(())
    }

    /// The image, row-major.
    pub fn pixels(&self) -> &[P] {
        &self.pixels
    }
}
