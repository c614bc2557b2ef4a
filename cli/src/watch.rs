//! Printing a status once, or again every few seconds (`--watch`), with
//! sparklines of chosen fields over the last polls under the table.

use crate::fields::{self, Fields};
use std::collections::VecDeque;
use std::io::IsTerminal;
use std::time::{Duration, Instant};

/// The shortest `--watch` period.
const MIN_PERIOD: Duration = Duration::from_millis(100);
/// Polls a sparkline shows.
const HISTORY: usize = 60;
/// Sparkline levels, lowest first.
const BARS: [char; 8] = ['▁', '▂', '▃', '▄', '▅', '▆', '▇', '█'];

/// What `--watch` plots under the table.
#[derive(Clone, Copy, Debug)]
pub enum Trend {
    /// A numeric field as it is.
    Value(&'static str),
    /// A counter field's growth per second between polls.
    PerSecond(&'static str),
}

impl Trend {
    fn label(self) -> String {
        match self {
            Self::Value(name) => name.to_string(),
            Self::PerSecond(name) => format!("{name}/s"),
        }
    }

    fn field(self) -> &'static str {
        match self {
            Self::Value(name) | Self::PerSecond(name) => name,
        }
    }
}

/// The recent values of the trends.
struct Trends {
    trends: Vec<Trend>,
    last: Option<(Instant, Vec<Option<f64>>)>,
    history: Vec<VecDeque<f64>>,
}

impl Trends {
    fn new(trends: &[Trend]) -> Self {
        Self {
            trends: trends.to_vec(),
            last: None,
            history: vec![VecDeque::with_capacity(HISTORY); trends.len()],
        }
    }

    /// Takes the trends' values from `fields`, polled at `at`.
    fn record(&mut self, fields: &Fields, at: Instant) {
        let now: Vec<Option<f64>> = self
            .trends
            .iter()
            .map(|t| {
                fields
                    .iter()
                    .find(|(name, _)| *name == t.field())
                    .and_then(|(_, v)| v.as_f64())
            })
            .collect();
        for (k, trend) in self.trends.iter().enumerate() {
            let value = match trend {
                Trend::Value(_) => now[k],
                Trend::PerSecond(_) => self.last.as_ref().and_then(|(then, before)| {
                    let seconds = at.duration_since(*then).as_secs_f64();
                    let grown = now[k]? - before[k]?;
                    (seconds > 0.0).then(|| grown / seconds)
                }),
            };
            if let Some(value) = value.filter(|v| v.is_finite()) {
                let history = &mut self.history[k];
                if history.len() == HISTORY {
                    history.pop_front();
                }
                history.push_back(value);
            }
        }
        self.last = Some((at, now));
    }

    /// One line per trend: label, sparkline, last value and range.
    fn print(&self) {
        let width = self
            .trends
            .iter()
            .map(|t| t.label().len())
            .max()
            .unwrap_or(0);
        for (trend, history) in self.trends.iter().zip(&self.history) {
            let values: Vec<f64> = history.iter().copied().collect();
            let Some(&last) = values.last() else { continue };
            let (lo, hi) = range(&values);
            println!(
                "{:<width$}  {}  {last:.3} (range {lo:.3} to {hi:.3})",
                trend.label(),
                sparkline(&values, (lo, hi))
            );
        }
    }
}

/// The smallest and largest of `values`.
fn range(values: &[f64]) -> (f64, f64) {
    values
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        })
}

/// `values` as bars scaled over their `range` (all at the lowest level
/// when it is empty).
fn sparkline(values: &[f64], (lo, hi): (f64, f64)) -> String {
    values
        .iter()
        .map(|&v| {
            let level = if hi > lo {
                ((v - lo) / (hi - lo) * (BARS.len() - 1) as f64).round() as usize
            } else {
                0
            };
            BARS[level.min(BARS.len() - 1)]
        })
        .collect()
}

/// Prints what `poll` returns, once or every `watch` seconds until the
/// process is interrupted; on a terminal the screen is redrawn, otherwise
/// (and with `--json`) each poll is printed after the last. Watched as a
/// table, `trends` are plotted under it over the last 60 polls.
pub async fn repeat<F, Fut>(
    watch: Option<f64>,
    json: bool,
    trends: &[Trend],
    mut poll: F,
) -> anyhow::Result<()>
where
    F: FnMut() -> Fut,
    Fut: Future<Output = anyhow::Result<Fields>>,
{
    let Some(seconds) = watch else {
        fields::print(&poll().await?, json);
        return Ok(());
    };
    if !(seconds.is_finite() && seconds > 0.0) {
        anyhow::bail!("--watch {seconds}: give a period in seconds, above 0");
    }
    let period = Duration::from_secs_f64(seconds).max(MIN_PERIOD);
    let redraw = !json && std::io::stdout().is_terminal();
    let mut recent = Trends::new(trends);
    loop {
        let fields = poll().await?;
        recent.record(&fields, Instant::now());
        if redraw {
            print!("\x1b[2J\x1b[H");
        }
        fields::print(&fields, json);
        if !json {
            recent.print();
        }
        if !json && !redraw {
            println!();
        }
        tokio::time::sleep(period).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn sparklines_span_the_range_and_rates_come_from_counters() {
        let values = [0.0, 1.0, 2.0, 3.0, 7.0];
        assert_eq!(range(&values), (0.0, 7.0));
        assert_eq!(sparkline(&values, range(&values)), "▁▂▃▄█");
        assert_eq!(sparkline(&[5.0, 5.0], range(&[5.0, 5.0])), "▁▁");
        let mut trends = Trends::new(&[Trend::Value("success_rate"), Trend::PerSecond("updates")]);
        let start = Instant::now();
        for (k, (success, updates)) in [(0.1, 0), (0.5, 30), (0.9, 90)].into_iter().enumerate() {
            let fields: Fields = vec![
                ("success_rate", json!(success)),
                ("updates", json!(updates)),
            ];
            trends.record(&fields, start + Duration::from_secs(3 * k as u64));
        }
        assert_eq!(Vec::from(trends.history[0].clone()), [0.1, 0.5, 0.9]);
        // 30 updates in 3 s, then 60 in 3 s; none before the second poll.
        assert_eq!(Vec::from(trends.history[1].clone()), [10.0, 20.0]);
        for _ in 0..2 * HISTORY {
            trends.record(&vec![("success_rate", json!(1.0))], Instant::now());
        }
        assert_eq!(trends.history[0].len(), HISTORY);
    }
}
