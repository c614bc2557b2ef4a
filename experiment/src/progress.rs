//! The run's progress, from the learner's status: a progress bar on a
//! terminal, a line every half minute otherwise.

use indicatif::{ProgressBar, ProgressStyle};
use std::io::IsTerminal;
use std::time::{Duration, Instant};
use tweezer_proto::pb::LearnerStatus;

/// Seconds between plain progress lines when stderr is not a terminal.
const LINE_EVERY: Duration = Duration::from_secs(30);
/// The updates-per-second figure averages over about this long.
const RATE_WINDOW: Duration = Duration::from_secs(10);

/// Shows how training goes.
pub struct Progress {
    bar: Option<ProgressBar>,
    started: Instant,
    limit: Option<Duration>,
    last_line: Instant,
    rate: Rate,
}

/// Updates per second over a sliding window of status polls.
struct Rate {
    samples: std::collections::VecDeque<(Instant, u64)>,
}

impl Rate {
    fn push(&mut self, now: Instant, updates: u64) -> f64 {
        self.samples.push_back((now, updates));
        while self.samples.len() > 2 && now.duration_since(self.samples[1].0) >= RATE_WINDOW {
            self.samples.pop_front();
        }
        let (t0, u0) = self.samples[0];
        let seconds = now.duration_since(t0).as_secs_f64();
        if seconds > 0.0 {
            updates.saturating_sub(u0) as f64 / seconds
        } else {
            0.0
        }
    }
}

impl Progress {
    /// Progress of a run of at most `limit` (None: until stopped).
    pub fn new(limit: Option<Duration>) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = match limit {
                Some(limit) => {
                    let bar = ProgressBar::new(limit.as_secs().max(1));
                    bar.set_style(
                        ProgressStyle::with_template(
                            "{elapsed_precise} [{bar:24}] {eta_precise} left  {msg}",
                        )
                        .expect("a valid template")
                        .progress_chars("=> "),
                    );
                    bar
                }
                None => {
                    let bar = ProgressBar::new_spinner();
                    bar.set_style(
                        ProgressStyle::with_template("{spinner} {elapsed_precise}  {msg}")
                            .expect("a valid template"),
                    );
                    bar
                }
            };
            bar.enable_steady_tick(Duration::from_millis(250));
            bar
        });
        let now = Instant::now();
        Self {
            bar,
            started: now,
            limit,
            last_line: now,
            rate: Rate {
                samples: Default::default(),
            },
        }
    }

    /// Shows the learner's latest status.
    pub fn update(&mut self, status: &LearnerStatus) {
        let now = Instant::now();
        let updates_per_sec = self.rate.push(now, status.updates);
        let message = summary(status, updates_per_sec);
        let elapsed = now.duration_since(self.started);
        match &self.bar {
            Some(bar) => {
                bar.set_position(elapsed.as_secs());
                bar.set_message(message);
            }
            None if now.duration_since(self.last_line) >= LINE_EVERY => {
                self.last_line = now;
                let of = self
                    .limit
                    .map(|l| format!(" of {}", clock(l)))
                    .unwrap_or_default();
                eprintln!("[{}{of}] {message}", clock(elapsed));
            }
            None => {}
        }
    }

    /// Prints a line above the bar.
    pub fn say(&self, line: &str) {
        match &self.bar {
            Some(bar) => bar.println(line),
            None => eprintln!("{line}"),
        }
    }

    /// Removes the bar.
    pub fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

/// One line on how training goes.
fn summary(s: &LearnerStatus, updates_per_sec: f64) -> String {
    let phase = if s.explore_uniformly {
        " (exploring)"
    } else {
        ""
    };
    let learning = if s.episodes == 0 {
        "no episode yet".to_string()
    } else {
        format!(
            "return {:.0}, success {:.0}% (last 100 of {} episodes)",
            s.rolling_return,
            100.0 * s.success_rate,
            s.episodes
        )
    };
    format!(
        "{} steps{phase}, {} updates ({updates_per_sec:.1}/s), {learning}, snapshot v{}",
        s.steps_inserted, s.updates, s.latest_snapshot
    )
}

/// `h:mm:ss`.
pub fn clock(d: Duration) -> String {
    let s = d.as_secs();
    format!("{}:{:02}:{:02}", s / 3600, s / 60 % 60, s % 60)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rate_averages_over_the_window() {
        let t0 = Instant::now();
        let mut rate = Rate {
            samples: Default::default(),
        };
        assert_eq!(rate.push(t0, 0), 0.0);
        let r = rate.push(t0 + Duration::from_secs(2), 100);
        assert!((r - 50.0).abs() < 1e-9);
        // Samples older than the window drop out.
        for k in 3..30 {
            rate.push(t0 + Duration::from_secs(k), 100 + 10 * (k - 2));
        }
        let r = rate.push(t0 + Duration::from_secs(30), 380);
        assert!((r - 10.0).abs() < 1e-9, "{r}");
        assert_eq!(clock(Duration::from_secs(3725)), "1:02:05");
    }
}
