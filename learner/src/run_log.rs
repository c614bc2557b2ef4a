//! The run log (`metrics.jsonl`): one JSON object per line, each with a `kind`
//! (`update`, `episode`, `snapshot`, `checkpoint`) and the seconds since
//! the learner started.

use serde::Serialize;
use std::fs::{File, OpenOptions};
use std::io::{self, BufWriter, Write};
use std::path::Path;
use std::sync::Mutex;
use std::time::Instant;

/// Appends lines to `metrics.jsonl`.
#[derive(Debug)]
pub struct RunLog {
    file: Option<Mutex<BufWriter<File>>>,
    started: Instant,
}

#[derive(Serialize)]
struct Line<'a, T: Serialize> {
    kind: &'a str,
    time_s: f64,
    #[serde(flatten)]
    fields: T,
}

impl RunLog {
    /// Appends to `path`, creating it if missing.
    pub fn append(path: &Path) -> io::Result<Self> {
        let file = OpenOptions::new().create(true).append(true).open(path)?;
        Ok(Self {
            file: Some(Mutex::new(BufWriter::new(file))),
            started: Instant::now(),
        })
    }

    /// A run log that goes nowhere (benchmarks and tests of other parts).
    pub fn discard() -> Self {
        Self {
            file: None,
            started: Instant::now(),
        }
    }

    /// Writes one line of `kind` with `fields` (a struct or map) and flushes
    /// it. A full disk costs lines, never the learner.
    pub fn write(&self, kind: &str, fields: impl Serialize) {
        let Some(file) = &self.file else { return };
        let line = Line {
            kind,
            time_s: self.started.elapsed().as_secs_f64(),
            fields,
        };
        let Ok(mut text) = serde_json::to_vec(&line) else {
            return;
        };
        text.push(b'\n');
        let mut file = file.lock().unwrap_or_else(|p| p.into_inner());
        if let Err(e) = file.write_all(&text).and_then(|()| file.flush()) {
            tracing::warn!(error = %e, "cannot write the metrics file");
        }
    }
}
