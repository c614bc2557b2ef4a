//! TensorBoard event files beside `metrics.jsonl`: every numeric field of a
//! run-log line becomes a scalar (`update/critic_loss`, `snapshot/
//! rolling_success_rate`, `episode/return`, ...) at the learner's update
//! count, so that `tensorboard --logdir runs/` shows a run live and overlays
//! a sweep. Each event is one TFRecord (length, masked CRC-32C of the
//! length, the `tensorflow.Event` protobuf, its masked CRC-32C) written
//! with a single `write`: a process killed at any moment leaves whole
//! records only.

use prost::Message;
use serde_json::Value;
use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

/// `tensorflow.Event`, the fields a scalar needs.
#[derive(Clone, PartialEq, Message)]
struct Event {
    #[prost(double, tag = "1")]
    wall_time: f64,
    #[prost(int64, tag = "2")]
    step: i64,
    #[prost(string, optional, tag = "3")]
    file_version: Option<String>,
    #[prost(message, optional, tag = "5")]
    summary: Option<Summary>,
}

/// `tensorflow.Summary`.
#[derive(Clone, PartialEq, Message)]
struct Summary {
    #[prost(message, repeated, tag = "1")]
    value: Vec<SummaryValue>,
}

/// `tensorflow.Summary.Value` holding a `simple_value` scalar.
#[derive(Clone, PartialEq, Message)]
struct SummaryValue {
    #[prost(string, tag = "1")]
    tag: String,
    #[prost(float, optional, tag = "2")]
    simple_value: Option<f32>,
}

/// CRC-32C as TFRecord stores it: rotated and offset, so that a CRC over
/// data that holds CRCs stays strong.
fn masked_crc(data: &[u8]) -> u32 {
    let crc = crc32c::crc32c(data);
    crc.rotate_right(15).wrapping_add(0xa282_ead8)
}

/// One TFRecord: the event's bytes framed by their length and checksums.
fn record(event: &Event) -> Vec<u8> {
    let data = event.encode_to_vec();
    let len = (data.len() as u64).to_le_bytes();
    let mut out = Vec::with_capacity(data.len() + 16);
    out.extend_from_slice(&len);
    out.extend_from_slice(&masked_crc(&len).to_le_bytes());
    out.extend_from_slice(&data);
    out.extend_from_slice(&masked_crc(&data).to_le_bytes());
    out
}

fn now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// An event file being appended to.
#[derive(Debug)]
pub struct EventFile {
    file: File,
    path: PathBuf,
    /// The learner's update count, the x axis of every scalar: updated by
    /// the lines that carry it, used by those that do not (episodes).
    step: i64,
    /// The previous update line's count and time, for updates per second.
    last_update: Option<(f64, f64)>,
}

impl EventFile {
    /// A new event file in `dir`
    /// (`events.out.tfevents.SECONDS.NAME.PID.N`), each process and start
    /// its own: `name` (the process) tells them apart.
    pub fn create(dir: &Path, name: &str) -> io::Result<Self> {
        static CREATED: AtomicU64 = AtomicU64::new(0);
        let wall = now();
        let path = dir.join(format!(
            "events.out.tfevents.{:010}.{name}.{}.{}",
            wall as u64,
            std::process::id(),
            CREATED.fetch_add(1, Ordering::Relaxed)
        ));
        let mut file = OpenOptions::new()
            .create_new(true)
            .append(true)
            .open(&path)?;
        file.write_all(&record(&Event {
            wall_time: wall,
            step: 0,
            file_version: Some("brain.Event:2".into()),
            summary: None,
        }))?;
        Ok(Self {
            file,
            path,
            step: 0,
            last_update: None,
        })
    }

    /// Where it is.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Writes the scalars of a run-log line of `kind` (its JSON object).
    pub fn write_line(&mut self, kind: &str, line: &Value) -> io::Result<()> {
        let Some(fields) = line.as_object() else {
            return Ok(());
        };
        if let Some(updates) = fields.get("updates").and_then(Value::as_i64) {
            self.step = updates;
        }
        let mut scalars: Vec<(String, f64)> = fields
            .iter()
            .filter(|(name, _)| !matches!(name.as_str(), "kind" | "time_s" | "updates"))
            .filter_map(|(name, v)| Some((format!("{kind}/{name}"), v.as_f64()?)))
            .collect();
        match kind {
            "update" => {
                let time = fields.get("time_s").and_then(Value::as_f64).unwrap_or(0.0);
                let updates = self.step as f64;
                if let Some((t0, u0)) = self.last_update
                    && time > t0
                {
                    scalars.push((
                        "update/updates_per_sec".into(),
                        (updates - u0) / (time - t0),
                    ));
                }
                self.last_update = Some((time, updates));
            }
            "episode" => {
                if let Some(outcome) = fields.get("outcome").and_then(Value::as_str) {
                    for name in ["success", "collision", "timeout"] {
                        let hit = if outcome == name { 1.0 } else { 0.0 };
                        scalars.push((format!("episode/{name}"), hit));
                    }
                }
            }
            _ => {}
        }
        if scalars.is_empty() {
            return Ok(());
        }
        let event = Event {
            wall_time: now(),
            step: self.step,
            file_version: None,
            summary: Some(Summary {
                value: scalars
                    .into_iter()
                    .map(|(tag, v)| SummaryValue {
                        tag,
                        simple_value: Some(v as f32),
                    })
                    .collect(),
            }),
        };
        self.file.write_all(&record(&event))
    }
}
