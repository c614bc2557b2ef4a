//! The paper's Fig. 4: reward per episode as a rolling mean, mean ± one
//! standard deviation across runs of the same setting, with the theoretical
//! maximum as a dashed line. Drawn as SVG, whose text needs no font files.

use crate::FigureError;
use plotters::prelude::*;
use std::path::Path;

/// Picture size in px.
const SIZE: (u32, u32) = (960, 600);

/// One setting's runs: each run's episode returns in order.
#[derive(Clone, Debug)]
pub struct Curve {
    /// The setting, as the legend shows it.
    pub label: String,
    /// Per run, the return of each episode.
    pub runs: Vec<Vec<f64>>,
}

/// What Fig. 4 shows besides the curves.
#[derive(Clone, Debug)]
pub struct RewardFigure {
    /// The title.
    pub title: String,
    /// Episodes in the rolling mean.
    pub window: usize,
    /// Theoretical maxima, each drawn dashed with its label: one per
    /// curve, in the curves' order, is drawn in that curve's colour; any
    /// other number in black.
    pub ideal: Vec<(String, f64)>,
}

/// The trailing mean of `values` over `window` entries (fewer at the start).
pub fn rolling_mean(values: &[f64], window: usize) -> Vec<f64> {
    let window = window.max(1);
    let mut sum = 0.0;
    values
        .iter()
        .enumerate()
        .map(|(i, &v)| {
            sum += v;
            if i >= window {
                sum -= values[i - window];
            }
            sum / (i + 1).min(window) as f64
        })
        .collect()
}

/// Mean and standard deviation across runs at each episode index that every
/// run reached.
fn band(runs: &[Vec<f64>]) -> Vec<(f64, f64)> {
    let length = runs.iter().map(Vec::len).min().unwrap_or(0);
    let n = runs.len() as f64;
    (0..length)
        .map(|i| {
            let mean = runs.iter().map(|r| r[i]).sum::<f64>() / n;
            let var = runs.iter().map(|r| (r[i] - mean).powi(2)).sum::<f64>() / n;
            (mean, var.sqrt())
        })
        .collect()
}

/// Draws Fig. 4 for `curves` into the SVG file `path`.
pub fn reward_figure(
    curves: &[Curve],
    figure: &RewardFigure,
    path: &Path,
) -> Result<(), FigureError> {
    let error = |reason: String| FigureError::Draw {
        path: path.display().to_string(),
        reason,
    };
    let bands: Vec<Vec<(f64, f64)>> = curves
        .iter()
        .map(|c| {
            let rolled: Vec<Vec<f64>> = c
                .runs
                .iter()
                .map(|r| rolling_mean(r, figure.window))
                .collect();
            band(&rolled)
        })
        .collect();
    let episodes = bands.iter().map(Vec::len).max().unwrap_or(0);
    if episodes == 0 {
        return Err(FigureError::Empty);
    }
    let mut lo = f64::INFINITY;
    let mut hi = f64::NEG_INFINITY;
    for &(mean, sd) in bands.iter().flatten() {
        lo = lo.min(mean - sd);
        hi = hi.max(mean + sd);
    }
    for &(_, ideal) in &figure.ideal {
        lo = lo.min(ideal);
        hi = hi.max(ideal);
    }
    let margin = 0.05 * (hi - lo).max(1.0);
    let draw = || -> Result<(), Box<dyn std::error::Error>> {
        let root = SVGBackend::new(path, SIZE).into_drawing_area();
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(&figure.title, ("sans-serif", 22))
            .margin(12)
            .x_label_area_size(44)
            .y_label_area_size(70)
            .build_cartesian_2d(0f64..episodes as f64, (lo - margin)..(hi + margin))?;
        chart
            .configure_mesh()
            .x_desc("episode")
            .y_desc(format!("reward ({}-episode rolling mean)", figure.window))
            .draw()?;
        let color_of = |k: usize| Palette99::pick(k).to_rgba();
        for (k, (curve, band)) in curves.iter().zip(&bands).enumerate() {
            let color = color_of(k);
            let upper = band
                .iter()
                .enumerate()
                .map(|(i, &(m, s))| (i as f64, m + s));
            let lower = band
                .iter()
                .enumerate()
                .map(|(i, &(m, s))| (i as f64, m - s));
            let outline: Vec<(f64, f64)> = upper.chain(lower.rev()).collect();
            chart.draw_series(std::iter::once(Polygon::new(outline, color.mix(0.2))))?;
            let label = format!(
                "{} ({} run{})",
                curve.label,
                curve.runs.len(),
                plural(curve.runs.len())
            );
            chart
                .draw_series(LineSeries::new(
                    band.iter().enumerate().map(|(i, &(m, _))| (i as f64, m)),
                    color.stroke_width(2),
                ))?
                .label(label)
                .legend(move |(x, y)| {
                    PathElement::new([(x, y), (x + 20, y)], color.stroke_width(2))
                });
        }
        let per_curve = figure.ideal.len() == curves.len() && curves.len() > 1;
        for (k, &(ref label, ideal)) in figure.ideal.iter().enumerate() {
            let color = if per_curve {
                color_of(k)
            } else {
                BLACK.to_rgba()
            };
            chart
                .draw_series(DashedLineSeries::new(
                    [(0.0, ideal), (episodes as f64, ideal)],
                    8,
                    6,
                    color.stroke_width(1),
                ))?
                .label(format!("theoretical maximum{label}"))
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], color));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.9))
            .border_style(BLACK)
            .draw()?;
        root.present()?;
        Ok(())
    };
    draw().map_err(|e| error(e.to_string()))
}

fn plural(n: usize) -> &'static str {
    if n == 1 { "" } else { "s" }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rolling_mean_averages_the_trailing_window() {
        assert_eq!(
            rolling_mean(&[1.0, 3.0, 5.0, 7.0], 2),
            vec![1.0, 2.0, 4.0, 6.0]
        );
    }

    #[test]
    fn band_spans_the_runs_every_run_reached() {
        let b = band(&[vec![1.0, 2.0, 9.0], vec![3.0, 4.0]]);
        assert_eq!(b, vec![(2.0, 1.0), (3.0, 1.0)]);
    }

    #[test]
    fn draws_curves_with_the_ideal_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fig4.svg");
        let curves = [Curve {
            label: "gamma 0.99".into(),
            runs: vec![(0..300).map(f64::from).collect(), vec![5.0; 250]],
        }];
        let figure = RewardFigure {
            title: "Fig. 4".into(),
            window: 100,
            ideal: vec![(String::new(), 400.0)],
        };
        reward_figure(&curves, &figure, &path).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(svg.starts_with("<svg"), "{}", &svg[..40]);
        assert!(svg.contains("gamma 0.99 (2 runs)"));
        assert!(svg.contains("theoretical maximum"));
        let empty = reward_figure(&[], &figure, &path).unwrap_err();
        assert!(matches!(empty, FigureError::Empty));
    }

    /// With one maximum per curve (a reward ablation), each dashed line
    /// takes its curve's colour, so the legend tells them apart.
    #[test]
    fn one_maximum_per_curve_is_drawn_in_its_colour() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fig4c.svg");
        let curves = ["all rewards", "no carry"].map(|label| Curve {
            label: label.into(),
            runs: vec![vec![100.0; 150]],
        });
        let figure = RewardFigure {
            title: "Fig. 4c".into(),
            window: 100,
            ideal: vec![
                (" (all rewards)".into(), 1_890.0),
                (" (no carry)".into(), 912.0),
            ],
        };
        reward_figure(&curves, &figure, &path).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        for k in 0..2 {
            let (r, g, b) = Palette99::pick(k).rgb();
            let thin = format!("stroke=\"#{r:02X}{g:02X}{b:02X}\" stroke-width=\"1\"");
            assert!(svg.contains(&thin), "no dashed line in curve {k}'s colour");
        }
    }
}
