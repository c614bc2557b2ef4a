//! A process's Prometheus metrics: histograms fed as things happen, and
//! figures read from the process's status at each scrape, exposed as
//! OpenMetrics text at `GET /metrics` (see [`crate::ServerSecurity::serve_metrics`]).

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
pub use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

/// One figure of a process's status, read at scrape time.
#[derive(Clone, Debug, PartialEq)]
pub struct Figure {
    /// Its name after the process's prefix (a counter's without `_total`).
    pub name: &'static str,
    /// What it measures.
    pub help: &'static str,
    /// Its value.
    pub value: FigureValue,
}

/// A figure's kind and value.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FigureValue {
    /// Only ever grows (until the process restarts).
    Counter(u64),
    /// Goes up and down.
    Gauge(f64),
}

impl Figure {
    /// A counter.
    pub fn counter(name: &'static str, help: &'static str, value: u64) -> Self {
        Self {
            name,
            help,
            value: FigureValue::Counter(value),
        }
    }

    /// A gauge.
    pub fn gauge(name: &'static str, help: &'static str, value: f64) -> Self {
        Self {
            name,
            help,
            value: FigureValue::Gauge(value),
        }
    }
}

/// Reads the figures at each scrape.
struct Figures(Box<dyn Fn() -> Vec<Figure> + Send + Sync>);

impl std::fmt::Debug for Figures {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Figures")
    }
}

impl Collector for Figures {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        for figure in (self.0)() {
            match figure.value {
                FigureValue::Counter(v) => {
                    let counter = ConstCounter::new(v);
                    let metric = encoder.encode_descriptor(
                        figure.name,
                        figure.help,
                        None,
                        counter.metric_type(),
                    )?;
                    counter.encode(metric)?;
                }
                FigureValue::Gauge(v) => {
                    let gauge = ConstGauge::new(v);
                    let metric = encoder.encode_descriptor(
                        figure.name,
                        figure.help,
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
        self.registry.register(name, help, histogram.clone());
    }

    /// Exposes the figures `read` returns, called at each scrape.
    pub fn figures(&mut self, read: impl Fn() -> Vec<Figure> + Send + Sync + 'static) {
        self.registry
            .register_collector(Box::new(Figures(Box::new(read))));
    }

    /// The metrics as OpenMetrics text.
    pub fn encode(&self) -> String {
        let mut text = String::new();
        prometheus_client::encoding::text::encode(&mut text, &self.registry)
            .expect("writing to a String cannot fail");
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
    fn figures_and_histograms_encode_as_openmetrics() {
        let mut metrics = Prometheus::new("tweezer_test");
        let histogram = Histogram::new(latency_buckets());
        metrics.histogram("update_seconds", "Time per update.", &histogram);
        metrics.figures(|| {
            vec![
                Figure::counter("steps_inserted", "Steps stored.", 42),
                Figure::gauge("buffer_fill", "Fraction full.", 0.5),
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
    }
}
