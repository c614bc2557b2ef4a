//! A process's Prometheus metrics: histograms fed as things happen, and samples
//! read from the process's status at each scrape, exposed at `GET /metrics`
//! (see [`crate::ServerSecurity::serve_metrics`]) as OpenMetrics text to a
//! scraper that asks for it (Prometheus does), and otherwise in Prometheus'
//! text format 0.0.4 (curl, `promtool check metrics`).

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
pub use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;
use std::collections::HashSet;

/// One sample of a process's status, read at scrape time.
#[derive(Clone, Debug, PartialEq)]
pub struct MetricSample {
    /// Its name after the process's prefix (a counter's without `_total`).
    pub name: &'static str,
    /// What it measures.
    pub help: &'static str,
    /// Its value.
    pub value: SampleValue,
}

/// A sample's kind and value.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SampleValue {
    /// Only ever grows (until the process restarts).
    Counter(u64),
    /// Goes up and down.
    Gauge(f64),
}

impl MetricSample {
    /// A counter.
    pub fn counter(name: &'static str, help: &'static str, value: u64) -> Self {
        Self {
            name,
            help,
            value: SampleValue::Counter(value),
        }
    }

    /// A gauge.
    pub fn gauge(name: &'static str, help: &'static str, value: f64) -> Self {
        Self {
            name,
            help,
            value: SampleValue::Gauge(value),
        }
    }
}

/// Reads the samples at each scrape.
struct Samples(Box<dyn Fn() -> Vec<MetricSample> + Send + Sync>);

impl std::fmt::Debug for Samples {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Samples")
    }
}

impl Collector for Samples {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        for sample in (self.0)() {
            match sample.value {
                SampleValue::Counter(v) => {
                    let counter = ConstCounter::new(v);
                    let metric = encoder.encode_descriptor(
                        sample.name,
                        sample.help,
                        None,
                        counter.metric_type(),
                    )?;
                    counter.encode(metric)?;
                }
                SampleValue::Gauge(v) => {
                    let gauge = ConstGauge::new(v);
                    let metric = encoder.encode_descriptor(
                        sample.name,
                        sample.help,
                        None,
                        gauge.metric_type(),
                    )?;
                    gauge.encode(metric)?;
                }
            }
        }
        Ok(())
    }
}

/// A process's metrics, every name under one prefix (`tweezer_learner`).
#[derive(Debug)]
pub struct Prometheus {
    registry: Registry,
}

impl Prometheus {
    /// No metrics yet, named `<prefix>_...`.
    pub fn new(prefix: &str) -> Self {
        Self {
            registry: Registry::with_prefix(prefix),
        }
    }

    /// Exposes `histogram` (a handle: whoever observes into a clone feeds
    /// it).
    pub fn histogram(&mut self, name: &str, help: &str, histogram: &Histogram) {
        // The encoder ends every help text with a full stop of its own.
        let help = help.trim_end_matches('.');
        self.registry.register(name, help, histogram.clone());
    }

    /// Exposes the samples `read` returns, called at each scrape.
    pub fn samples(&mut self, read: impl Fn() -> Vec<MetricSample> + Send + Sync + 'static) {
        self.registry
            .register_collector(Box::new(Samples(Box::new(read))));
    }

    /// The metrics as OpenMetrics text.
    pub fn encode(&self) -> String {
        let mut text = String::new();
        prometheus_client::encoding::text::encode(&mut text, &self.registry)
            .expect("writing to a String cannot fail");
        text
    }

    /// The metrics in Prometheus' text format 0.0.4: the OpenMetrics text
    /// with each counter's HELP and TYPE named as its sample is (with
    /// `_total`), and without the `# EOF` and `# UNIT` lines.
    pub fn encode_text(&self) -> String {
        let open = self.encode();
        let counters: HashSet<&str> = open
            .lines()
            .filter_map(|line| line.strip_prefix("# TYPE ")?.strip_suffix(" counter"))
            .collect();
        let mut text = String::with_capacity(open.len() + 16 * counters.len());
        for line in open.lines() {
            if line == "# EOF" || line.starts_with("# UNIT ") {
                continue;
            }
            let renamed = ["# HELP ", "# TYPE "].into_iter().find_map(|prefix| {
                let (name, rest) = line.strip_prefix(prefix)?.split_once(' ')?;
                counters
                    .contains(name)
                    .then(|| format!("{prefix}{name}_total {rest}"))
            });
            text.push_str(renamed.as_deref().unwrap_or(line));
            text.push('\n');
        }
        text
    }
}

/// Buckets from 0.5 ms to ~16 s, doubling: latencies of a step, a call
/// or an update.
pub fn latency_buckets() -> impl Iterator<Item = f64> {
    exponential_buckets(0.0005, 2.0, 16)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_and_histograms_encode_as_openmetrics() {
        let mut metrics = Prometheus::new("tweezer_test");
        let histogram = Histogram::new(latency_buckets());
        metrics.histogram("update_seconds", "Time per update.", &histogram);
        metrics.samples(|| {
            vec![
                MetricSample::counter("steps_inserted", "Steps stored.", 42),
                MetricSample::gauge("buffer_fill", "Fraction full.", 0.5),
            ]
        });
        histogram.observe(0.003);
        let text = metrics.encode();
        assert!(
            text.contains("# TYPE tweezer_test_steps_inserted counter"),
            "{text}"
        );
        assert!(
            text.contains("tweezer_test_steps_inserted_total 42"),
            "{text}"
        );
        assert!(text.contains("tweezer_test_buffer_fill 0.5"), "{text}");
        assert!(
            text.contains("tweezer_test_update_seconds_count 1"),
            "{text}"
        );
        assert!(text.ends_with("# EOF\n"), "{text}");
        assert!(text.contains("# HELP tweezer_test_update_seconds Time per update.\n"));

        let text = metrics.encode_text();
        assert!(
            text.contains("# HELP tweezer_test_steps_inserted_total Steps stored.\n"),
            "{text}"
        );
        assert!(
            text.contains("# TYPE tweezer_test_steps_inserted_total counter\n"),
            "{text}"
        );
        assert!(text.contains("# TYPE tweezer_test_buffer_fill gauge\n"));
        assert!(text.contains("# TYPE tweezer_test_update_seconds histogram\n"));
        assert!(!text.contains("# EOF"), "{text}");
    }
}
