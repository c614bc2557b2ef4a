//! The run log (`metrics.jsonl`): one JSON object per line, each with a `kind`
//! (`update`, `episode`, `snapshot`, `checkpoint`) and the seconds since
//! the learner started; and the same numbers as TensorBoard scalars in an
//! event file beside it.

use crate::persistence::tensorboard::EventFile;
use serde::Serialize;
use std::fs::{File, OpenOptions};
use std::io::{self, BufWriter, Write};
use std::path::Path;
use std::sync::Mutex;
use std::time::Instant;

/// Appends lines to `metrics.jsonl` and scalars to an event file.
#[derive(Debug)]
pub struct RunLog {
    file: Option<Mutex<Files>>,
    started: Instant,
}

#[derive(Debug)]
struct Files {
    lines: BufWriter<File>,
    events: Option<EventFile>,
}

#[derive(Serialize)]
struct Line<'a, T: Serialize> {
    kind: &'a str,
    time_s: f64,
    #[serde(flatten)]
    fields: T,
}

impl RunLog {
    /// Appends to `path`, creating it if missing, and to a new event file
    /// of `process` (`learner`, `experiment`) beside it. Without an event
    /// file (a directory it cannot be made in) the run log goes on alone.
    pub fn append(path: &Path, process: &str) -> io::Result<Self> {
        let file = OpenOptions::new().create(true).append(true).open(path)?;
        let dir = path.parent().unwrap_or(Path::new("."));
        let events = EventFile::create(dir, process)
            .inspect_err(
                |e| tracing::warn!(error = %e, dir = %dir.display(), "no TensorBoard event file"),
            )
            .ok();
        Ok(Self {
            file: Some(Mutex::new(Files {
                lines: BufWriter::new(file),
                events,
            })),
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
        let value = serde_json::from_slice(&text).unwrap_or_default();
        text.push(b'\n');
        let mut files = file.lock().unwrap_or_else(|p| p.into_inner());
        let Files { lines, events } = &mut *files;
        if let Err(e) = lines.write_all(&text).and_then(|()| lines.flush()) {
            tracing::warn!(error = %e, "cannot write the metrics file");
        }
        if let Some(events) = events
            && let Err(e) = events.write_line(kind, &value)
        {
            tracing::warn!(error = %e, path = %events.path().display(), "cannot write the TensorBoard event file");
        }
    }
}
