//! Episodes drawn as PNG scenes in world px: the trapped sphere and its path
//! in red, free spheres in green, targets as blue rings, the field of view as
//! a rectangle (Figs. 5 and 6).

use crate::FigureError;
use plotters::prelude::*;
use std::path::Path;
use tweezer_gym::Trajectory;

/// Side of one panel, in picture pixels.
const PANEL_PX: u32 = 640;
/// Gap between panels, in picture pixels.
const GAP_PX: u32 = 16;
/// World px of empty border around what a panel must show.
const BORDER_PX: f64 = 150.0;

const FREE: RGBColor = RGBColor(0, 150, 0);
const TRAPPED: RGBColor = RGBColor(210, 0, 0);
const TARGET: RGBColor = RGBColor(0, 70, 230);
const FOV: RGBColor = RGBColor(40, 40, 40);

/// The square world region a set of panels shows.
#[derive(Clone, Copy, Debug)]
struct View {
    min: [f64; 2],
    side: f64,
}

impl View {
    /// The smallest square holding every FOV rectangle, target and path point
    /// of `trajectories`, with a border.
    fn around(trajectories: &[&Trajectory]) -> Self {
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        let mut include = |p: [f64; 2], half: [f64; 2]| {
            for a in 0..2 {
                lo[a] = lo[a].min(p[a] - half[a]);
                hi[a] = hi[a].max(p[a] + half[a]);
            }
        };
        for t in trajectories {
            let half_fov = [t.fov_px[0] / 2.0, t.fov_px[1] / 2.0];
            include(t.trap[0], half_fov);
            include(*t.trap.last().expect("a trajectory has a start"), half_fov);
            include(t.target, [t.radius; 2]);
            for &p in &t.trap {
                include(p, [t.radius; 2]);
            }
        }
        let side = (hi[0] - lo[0]).max(hi[1] - lo[1]) + 2.0 * BORDER_PX;
        let centre = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0];
        Self {
            min: [centre[0] - side / 2.0, centre[1] - side / 2.0],
            side,
        }
    }

    fn px(&self, p: [f64; 2]) -> (i32, i32) {
        let k = f64::from(PANEL_PX) / self.side;
        (
            ((p[0] - self.min[0]) * k).round() as i32,
            ((p[1] - self.min[1]) * k).round() as i32,
        )
    }

    fn length(&self, world: f64) -> i32 {
        (world * f64::from(PANEL_PX) / self.side).round().max(1.0) as i32
    }

    fn contains(&self, p: [f64; 2], margin: f64) -> bool {
        (0..2).all(|a| p[a] >= self.min[a] - margin && p[a] <= self.min[a] + self.side + margin)
    }
}

type Panel<'a> = DrawingArea<BitMapBackend<'a>, plotters::coord::Shift>;

/// Draws into one panel; errors are the backend's, as text.
struct Painter<'p, 'a> {
    panel: &'p Panel<'a>,
    view: View,
}

impl Painter<'_, '_> {
    fn result<E: std::fmt::Display>(r: Result<(), E>) -> Result<(), String> {
        r.map_err(|e| e.to_string())
    }

    fn circle(
        &self,
        c: [f64; 2],
        radius: f64,
        color: RGBColor,
        filled: bool,
    ) -> Result<(), String> {
        let style = if filled {
            color.filled()
        } else {
            color.stroke_width(2)
        };
        Self::result(self.panel.draw(&Circle::new(
            self.view.px(c),
            self.view.length(radius),
            style,
        )))
    }

    fn path(&self, points: &[[f64; 2]], color: RGBColor, width: u32) -> Result<(), String> {
        let pts: Vec<_> = points.iter().map(|&p| self.view.px(p)).collect();
        Self::result(
            self.panel
                .draw(&PathElement::new(pts, color.stroke_width(width))),
        )
    }

    fn fov(&self, centre: [f64; 2], fov: [f64; 2]) -> Result<(), String> {
        let a = self
            .view
            .px([centre[0] - fov[0] / 2.0, centre[1] - fov[1] / 2.0]);
        let b = self
            .view
            .px([centre[0] + fov[0] / 2.0, centre[1] + fov[1] / 2.0]);
        Self::result(
            self.panel
                .draw(&Rectangle::new([a, b], FOV.stroke_width(2))),
        )
    }

    /// Free spheres at step `t` of `trajectory` (its last step if shorter).
    fn spheres_at(&self, trajectory: &Trajectory, t: usize) -> Result<(), String> {
        let frame = &trajectory.spheres[t.min(trajectory.spheres.len() - 1)];
        for &p in frame {
            if self.view.contains(p, trajectory.radius) {
                self.circle(p, trajectory.radius, FREE, false)?;
            }
        }
        Ok(())
    }

    /// Every free sphere's path over `steps` steps of `trajectory`.
    fn sphere_paths(&self, trajectory: &Trajectory, steps: usize) -> Result<(), String> {
        let steps = steps.min(trajectory.spheres.len());
        let count = trajectory.spheres[0].len();
        for k in 0..count {
            let path: Vec<[f64; 2]> = (0..steps).map(|t| trajectory.spheres[t][k]).collect();
            if path.iter().any(|&p| self.view.contains(p, 0.0)) {
                self.path(&path, FREE, 1)?;
            }
        }
        Ok(())
    }
}

/// Draws three panels side by side into `path`.
fn three_panels(
    path: &Path,
    view: View,
    draw: impl Fn(usize, &Painter) -> Result<(), String>,
) -> Result<(), FigureError> {
    let error = |reason: String| FigureError::Draw {
        path: path.display().to_string(),
        reason,
    };
    let width = 3 * PANEL_PX + 2 * GAP_PX;
    let root = BitMapBackend::new(path, (width, PANEL_PX)).into_drawing_area();
    root.fill(&RGBColor(200, 200, 200))
        .map_err(|e| error(e.to_string()))?;
    for k in 0..3u32 {
        let x0 = (k * (PANEL_PX + GAP_PX)) as i32;
        let panel = root.clone().shrink((x0, 0), (PANEL_PX, PANEL_PX));
        panel.fill(&WHITE).map_err(|e| error(e.to_string()))?;
        draw(
            k as usize,
            &Painter {
                panel: &panel,
                view,
            },
        )
        .map_err(error)?;
    }
    root.present().map_err(|e| error(e.to_string()))
}

/// The paper's Fig. 5 for one episode: a) the trapped sphere's path and the
/// free spheres' motion, b) the start, with the field of view and the target,
/// c) the end.
pub fn episode_figure(trajectory: &Trajectory, path: &Path) -> Result<(), FigureError> {
    let t = trajectory;
    let view = View::around(&[t]);
    let end = t.trap.len() - 1;
    three_panels(path, view, |panel, p| {
        match panel {
            0 => {
                p.sphere_paths(t, t.trap.len())?;
                p.path(&t.trap, TRAPPED, 3)?;
            }
            1 => {
                p.spheres_at(t, 0)?;
                p.fov(t.trap[0], t.fov_px)?;
            }
            _ => {
                p.spheres_at(t, end)?;
                p.path(&t.trap, TRAPPED, 2)?;
                p.fov(t.trap[end], t.fov_px)?;
            }
        }
        p.circle(t.target, t.radius, TARGET, false)?;
        let trap = if panel == 1 { t.trap[0] } else { t.trap[end] };
        p.circle(trap, t.radius, TRAPPED, true)
    })
}

/// The paper's Fig. 6: episodes from one seed with different targets, whose
/// free spheres move identically, overlaid: a) all paths, b) the start with
/// every target and the field of view, c) the end of every episode.
pub fn targets_figure(trajectories: &[Trajectory], path: &Path) -> Result<(), FigureError> {
    let longest = trajectories
        .iter()
        .max_by_key(|t| t.trap.len())
        .ok_or(FigureError::Empty)?;
    let all: Vec<&Trajectory> = trajectories.iter().collect();
    let view = View::around(&all);
    let steps = longest.trap.len();
    three_panels(path, view, |panel, p| {
        match panel {
            0 => p.sphere_paths(longest, steps)?,
            1 => {
                p.spheres_at(longest, 0)?;
                p.fov(longest.trap[0], longest.fov_px)?;
            }
            _ => p.spheres_at(longest, steps - 1)?,
        }
        for t in trajectories {
            p.circle(t.target, t.radius, TARGET, false)?;
            if panel != 1 {
                p.path(&t.trap, TRAPPED, 2)?;
                p.circle(*t.trap.last().expect("non-empty"), t.radius, TRAPPED, true)?;
            }
        }
        p.circle(longest.trap[0], longest.radius, TRAPPED, true)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use tweezer_gym::{EnvConfig, Greedy, Target, record};

    fn is_png(path: &Path) -> bool {
        let bytes = std::fs::read(path).unwrap();
        bytes.len() > 1000 && bytes.starts_with(b"\x89PNG\r\n\x1a\n")
    }

    #[test]
    fn draws_both_figures() {
        let dir = tempfile::tempdir().unwrap();
        let config = EnvConfig::default();
        let one = record(&config, 3, Target::Random, &mut Greedy).unwrap();
        episode_figure(&one, &dir.path().join("fig5.png")).unwrap();
        assert!(is_png(&dir.path().join("fig5.png")));
        let twelve: Vec<_> = (0..12)
            .map(|k| {
                record(
                    &config,
                    3,
                    Target::Angle(f64::from(k) * std::f64::consts::FRAC_PI_6),
                    &mut Greedy,
                )
                .unwrap()
            })
            .collect();
        targets_figure(&twelve, &dir.path().join("fig6.png")).unwrap();
        assert!(is_png(&dir.path().join("fig6.png")));
    }

    #[test]
    fn unwritable_paths_are_errors() {
        let config = EnvConfig::default();
        let one = record(&config, 3, Target::Random, &mut Greedy).unwrap();
        let err = episode_figure(&one, Path::new("/nonexistent-dir/fig.png")).unwrap_err();
        assert!(
            err.to_string().contains("/nonexistent-dir/fig.png"),
            "{err}"
        );
        assert!(matches!(
            targets_figure(&[], Path::new("x.png")),
            Err(FigureError::Empty)
        ));
    }
}
