//! A camera that replays a directory of frame files in name order.

use super::{Camera, CameraError, GrayFrame, read_frame};
use std::path::{Path, PathBuf};

/// Replays the PNG and TIFF files of a directory, sorted by name.
#[derive(Debug)]
pub struct ReplayCamera {
    dir: PathBuf,
    files: Vec<PathBuf>,
    next: usize,
    looping: bool,
    size: [usize; 2],
}

impl ReplayCamera {
    /// Lists the frames of `dir` and reads the first to learn their size;
    /// with `looping` the sequence repeats, else `grab` fails after the last.
    pub fn open(dir: &Path, looping: bool) -> Result<Self, CameraError> {
        let error = |reason: String| CameraError::Read {
            path: dir.to_path_buf(),
            reason,
        };
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(|e| error(e.to_string()))?
            .filter_map(|entry| entry.ok().map(|e| e.path()))
            .filter(|path| is_frame_file(path))
            .collect();
        files.sort();
        let first = files
            .first()
            .ok_or_else(|| error("no .png, .tif or .tiff files".into()))?;
        let frame = read_frame(first)?;
        Ok(Self {
            dir: dir.to_path_buf(),
            size: [frame.width(), frame.height()],
            files,
            next: 0,
            looping,
        })
    }

    /// How many frames the directory holds.
    pub fn len(&self) -> usize {
        self.files.len()
    }

    /// Whether the directory holds no frames (never, once opened).
    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }
}

/// Whether `path` names a PNG or TIFF file.
fn is_frame_file(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["png", "tif", "tiff"].contains(&e.to_ascii_lowercase().as_str()))
}

impl Camera for ReplayCamera {
    fn size(&self) -> [usize; 2] {
        self.size
    }

    fn grab(&mut self) -> Result<GrayFrame, CameraError> {
        if self.next == self.files.len() {
            if !self.looping {
                return Err(CameraError::Exhausted(self.dir.clone()));
            }
            self.next = 0;
        }
        let path = &self.files[self.next];
        self.next += 1;
        let frame = read_frame(path)?;
        let got = [frame.width(), frame.height()];
        if got != self.size {
            return Err(CameraError::Size {
                what: path.display().to_string(),
                got,
                want: self.size,
            });
        }
        Ok(frame)
    }
}
