//! Episode records: one JSON-lines file per episode (a header, every step's
//! centres, vector, action, positions and timing, and how it ended) and a
//! picture of it like the paper's Figs. 7 and 8.

use crate::control::{EpisodeSummary, StepLog};
use serde::Serialize;
use serde_json::json;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use tweezer_figures::{FieldEpisode, field_figure};

/// Steps between the snapshots of the explored field drawn in the picture.
const VIEW_EVERY: u32 = 10;

/// What an episode was asked to do.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EpisodeHeader {
    /// Episode number since the agent started.
    pub episode: u64,
    /// The policy's description.
    pub policy: String,
    /// Its snapshot version (0: none).
    pub policy_version: u64,
    /// Target relative to the trap's start, image axes, px.
    pub target_offset_px: [f64; 2],
    /// Control rate, Hz.
    pub rate_hz: f64,
    /// The twin's episode seed, when run against the twin.
    pub twin_seed: Option<u64>,
}

/// Where an episode's record went.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RecordFiles {
    /// The JSON-lines record.
    pub record: PathBuf,
    /// The picture.
    pub picture: PathBuf,
}

/// A record that could not be written.
#[derive(Debug, thiserror::Error)]
#[error("cannot write the episode record {path}: {reason}")]
pub struct RecordError {
    path: String,
    reason: String,
}

/// Writes one episode's record as it runs.
#[derive(Debug)]
pub struct EpisodeRecorder {
    record: PathBuf,
    picture: PathBuf,
    writer: BufWriter<File>,
    field: FieldEpisode,
    failed: Option<std::io::Error>,
}

impl EpisodeRecorder {
    /// Starts `dir/episode-NNNNNN.jsonl` with its header; `fov_px` and
    /// `radius_px` are the environment's.
    pub fn create(
        dir: &Path,
        header: &EpisodeHeader,
        fov_px: [f64; 2],
        radius_px: f64,
    ) -> Result<Self, RecordError> {
        let stem = dir.join(format!("episode-{:06}", header.episode));
        let record = stem.with_extension("jsonl");
        let error = |e: std::io::Error| RecordError {
            path: record.display().to_string(),
            reason: e.to_string(),
        };
        std::fs::create_dir_all(dir).map_err(error)?;
        let mut writer = BufWriter::new(File::create(&record).map_err(error)?);
        writeln!(writer, "{}", json!({ "header": header })).map_err(error)?;
        Ok(Self {
            picture: stem.with_extension("png"),
            record,
            writer,
            field: FieldEpisode {
                fov_px,
                radius: radius_px,
                ..FieldEpisode::default()
            },
            failed: None,
        })
    }

    /// Appends a step (a write error is kept for [`EpisodeRecorder::finish`]).
    pub fn step(&mut self, log: &StepLog) {
        if self.failed.is_none()
            && let Err(e) = writeln!(self.writer, "{}", json!({ "step": log }))
        {
            self.failed = Some(e);
        }
        let p = log.position_px;
        self.field.path.push(p);
        if log.step.is_multiple_of(VIEW_EVERY) {
            let [hw, hh] = self.field.fov_px.map(|v| v / 2.0);
            let seen = log.centres[..log.detected]
                .iter()
                .map(|c| [p[0] + f64::from(c[0]) - hw, p[1] + f64::from(c[1]) - hh])
                .collect();
            self.field.views.push((p, seen));
        }
    }

    /// Writes the end line and the picture (obstacles in world px).
    pub fn finish(
        mut self,
        summary: &EpisodeSummary,
        obstacles: &[[f64; 2]],
    ) -> Result<RecordFiles, RecordError> {
        let error = |path: &Path, reason: String| RecordError {
            path: path.display().to_string(),
            reason,
        };
        let ended = writeln!(self.writer, "{}", json!({ "end": summary }));
        if let Some(e) = self.failed.take().or(ended.err()) {
            return Err(error(&self.record, e.to_string()));
        }
        self.writer
            .flush()
            .and_then(|()| self.writer.get_ref().sync_all())
            .map_err(|e| error(&self.record, e.to_string()))?;
        self.field.target = summary.target_px;
        if self.field.path.is_empty() {
            self.field.path.push(summary.start_px);
        }
        self.field.path.push(summary.end_px);
        let [hw, hh] = self.field.fov_px.map(|v| v / 2.0);
        // Only the obstacles near the explored field are drawn.
        let near = |o: &&[f64; 2]| {
            self.field
                .path
                .iter()
                .any(|p| (o[0] - p[0]).abs() <= 2.0 * hw && (o[1] - p[1]).abs() <= 2.0 * hh)
        };
        self.field.obstacles = obstacles.iter().filter(near).copied().collect();
        field_figure(&self.field, &self.picture)
            .map_err(|e| error(&self.picture, e.to_string()))?;
        Ok(RecordFiles {
            record: self.record,
            picture: self.picture,
        })
    }
}
