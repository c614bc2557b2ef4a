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
const EXPLORED: RGBColor = RGBColor(170, 170, 170);
const OBSTACLE: RGBColor = RGBColor(240, 150, 0);

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
        Self::around_boxes(trajectories.iter().flat_map(|t| {
            let half_fov = [t.fov_px[0] / 2.0, t.fov_px[1] / 2.0];
            let ends = [t.trap[0], *t.trap.last().expect("a trajectory has a start")];
            ends.into_iter()
                .map(move |p| (p, half_fov))
                .chain(std::iter::once((t.target, [t.radius; 2])))
                .chain(t.trap.iter().map(|&p| (p, [t.radius; 2])))
        }))
    }

    /// The smallest square holding every box (centre, half size), with a
    /// border.
    fn around_boxes(boxes: impl IntoIterator<Item = ([f64; 2], [f64; 2])>) -> Self {
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for (p, half) in boxes {
            for a in 0..2 {
                lo[a] = lo[a].min(p[a] - half[a]);
                hi[a] = hi[a].max(p[a] + half[a]);
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
        self.rectangle(centre, fov, FOV)
    }

    fn rectangle(&self, centre: [f64; 2], fov: [f64; 2], color: RGBColor) -> Result<(), String> {
        let a = self
            .view
            .px([centre[0] - fov[0] / 2.0, centre[1] - fov[1] / 2.0]);
        let b = self
            .view
            .px([centre[0] + fov[0] / 2.0, centre[1] + fov[1] / 2.0]);
        Self::result(
            self.panel
                .draw(&Rectangle::new([a, b], color.stroke_width(2))),
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
    panels(path, 3, view, draw)
}

/// Draws `count` panels side by side into `path`.
fn panels(
    path: &Path,
    count: u32,
    view: View,
    draw: impl Fn(usize, &Painter) -> Result<(), String>,
) -> Result<(), FigureError> {
    let error = |reason: String| FigureError::Draw {
        path: path.display().to_string(),
        reason,
    };
    let width = count * PANEL_PX + (count - 1) * GAP_PX;
    let root = BitMapBackend::new(path, (width, PANEL_PX)).into_drawing_area();
    root.fill(&RGBColor(200, 200, 200))
        .map_err(|e| error(e.to_string()))?;
    for k in 0..count {
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

/// An episode on the instrument, in world px, as the paper's Figs. 7 and 8
/// draw it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FieldEpisode {
    /// Field of view, px.
    pub fov_px: [f64; 2],
    /// Sphere radius, px.
    pub radius: f64,
    /// The trap at every step.
    pub path: Vec<[f64; 2]>,
    /// Snapshots along the way: the trap, and the spheres detected then.
    pub views: Vec<([f64; 2], Vec<[f64; 2]>)>,
    /// Virtual obstacles.
    pub obstacles: Vec<[f64; 2]>,
    /// The target.
    pub target: [f64; 2],
}

/// The paper's Figs. 7 and 8 for one instrument episode: the explored field
/// (a field-of-view rectangle and the detected spheres at each snapshot),
/// the virtual obstacles near it, the trap's path and the target.
pub fn field_figure(episode: &FieldEpisode, path: &Path) -> Result<(), FigureError> {
    let e = episode;
    let start = *e.path.first().ok_or(FigureError::Empty)?;
    let half_fov = [e.fov_px[0] / 2.0, e.fov_px[1] / 2.0];
    let view = View::around_boxes(
        e.views
            .iter()
            .map(|v| (v.0, half_fov))
            .chain([(start, half_fov), (e.target, [e.radius; 2])])
            .chain(e.path.iter().map(|&p| (p, [e.radius; 2]))),
    );
    panels(path, 1, view, |_, p| {
        for &o in &e.obstacles {
            if view.contains(o, e.radius) {
                p.circle(o, e.radius, OBSTACLE, true)?;
            }
        }
        for (trap, spheres) in &e.views {
            p.rectangle(*trap, e.fov_px, EXPLORED)?;
            for &s in spheres {
                p.circle(s, e.radius, FREE, false)?;
            }
        }
        p.fov(start, e.fov_px)?;
        p.circle(e.target, e.radius, TARGET, false)?;
        p.path(&e.path, TRAPPED, 3)?;
        p.circle(*e.path.last().expect("non-empty"), e.radius, TRAPPED, true)
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
    fn an_episode_and_twelve_targets_draw_as_png_figures() {
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
    fn draws_an_instrument_episode() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("field.png");
        let episode = FieldEpisode {
            fov_px: [1280.0, 1024.0],
            radius: 27.0,
            path: (0..100).map(|k| [10.0 * k as f64, 0.0]).collect(),
            views: vec![([0.0, 0.0], vec![[100.0, 100.0]]), ([500.0, 0.0], vec![])],
            obstacles: vec![[500.0, 200.0], [1e6, 0.0]],
            target: [1000.0, 0.0],
        };
        field_figure(&episode, &file).unwrap();
        assert!(is_png(&file));
        assert!(matches!(
            field_figure(&FieldEpisode::default(), &file),
            Err(FigureError::Empty)
        ));
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
