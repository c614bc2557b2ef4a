//! Cameras: a grayscale frame type and the [`Camera`] trait the control loop
//! grabs frames through, with backends that replay frames from files
//! ([`ReplayCamera`]), read frames another program writes
//! ([`frame_stream`]) and drive GenICam cameras through Aravis
//! ([`genicam`]); the digital twin's camera lives in the hardware agent.

mod files;
pub mod frame_stream;
pub mod genicam;
mod replay;

pub use files::{read_frame, write_frame};
pub use replay::ReplayCamera;

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tweezer_config::ConfigError;

/// The instant of a moment given as time since the Unix epoch (a camera's
/// or a program's timestamp), no later than now.
pub(crate) fn instant_of_unix(since_epoch: Duration) -> Instant {
    let now = Instant::now();
    let ago = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default()
        .saturating_sub(since_epoch);
    now.checked_sub(ago).unwrap_or(now)
}

/// One grayscale camera frame, row-major, x right and y down.
#[derive(Clone, Debug, PartialEq)]
pub struct GrayFrame {
    width: usize,
    height: usize,
    /// The largest value a pixel can take (255 for 8-bit frames, 4095 for
    /// 12-bit, 65535 for 16-bit).
    max_value: u16,
    pixels: Vec<u16>,
}

impl GrayFrame {
    /// A frame of `width` x `height` pixels; `None` if the pixel count does
    /// not match or a pixel exceeds `max_value`.
    pub fn new(width: usize, height: usize, max_value: u16, pixels: Vec<u16>) -> Option<Self> {
        (width > 0
            && height > 0
            && pixels.len() == width * height
            && pixels.iter().all(|&p| p <= max_value))
        .then_some(Self {
            width,
            height,
            max_value,
            pixels,
        })
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The largest value a pixel can take.
    pub fn max_value(&self) -> u16 {
        self.max_value
    }

    /// The pixels, row after row.
    pub fn pixels(&self) -> &[u16] {
        &self.pixels
    }
}

/// Why a camera gave no frame.
#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    /// A frame file could not be read.
    #[error("cannot read frame {path}: {reason}")]
    Read {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
    /// A frame file could not be written.
    #[error("cannot write frame {path}: {reason}")]
    Write {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
    /// A frame has a size other than the camera's.
    #[error("frame {what} is {got:?} px, the camera's frames are {want:?} px")]
    Size {
        /// Which frame.
        what: String,
        /// Its width and height.
        got: [usize; 2],
        /// The expected width and height.
        want: [usize; 2],
    },
    /// A replayed sequence has no more frames.
    #[error("no more frames in {0} (replayed once; set `loop = true` to repeat)")]
    Exhausted(PathBuf),
    /// No frame came within the allowed time.
    #[error("the camera gave no frame within {0:?}")]
    Stalled(std::time::Duration),
    /// A camera setting was refused or could not be applied.
    #[error("camera setting {setting}: {reason}")]
    Setting {
        /// The setting, as the configuration names it.
        setting: String,
        /// What is wrong and what to do.
        reason: String,
    },
    /// The camera could not be reached, or stopped answering.
    #[error("{0}")]
    Device(String),
}

impl CameraError {
    /// A setting of the `table` configuration table that its check refused.
    pub fn setting(table: &str, e: ConfigError) -> Self {
        match e {
            ConfigError::Invalid { field, reason } => Self::Setting {
                setting: format!("{table}.{field}"),
                reason,
            },
            other => Self::Setting {
                setting: table.into(),
                reason: other.to_string(),
            },
        }
    }
}

/// A source of frames: a real camera, a replayed directory, or the digital
/// twin. `grab` returns a frame captured after the previous call returned:
/// a live camera waits for its next frame.
pub trait Camera: Send {
    /// Width and height of every frame, px.
    fn size(&self) -> [usize; 2];

    /// The next frame.
    fn grab(&mut self) -> Result<GrayFrame, CameraError>;

    /// When the frame `grab` last returned reached this computer, if the
    /// camera knows (a live camera's buffer timestamp); the loop's latency
    /// counts from there, else from the end of `grab`.
    fn captured(&self) -> Option<Instant> {
        None
    }

    /// Readies the camera for an episode: reconnects a camera that was
    /// lost and starts acquiring.
    fn start(&mut self) -> Result<(), CameraError> {
        Ok(())
    }

    /// Ends acquisition after an episode.
    fn stop(&mut self) {}
}

/// What a camera delivered and refused, for the metrics: frames that
/// arrive incomplete or that never arrive are counted and never reach
/// segmentation.
#[derive(Debug, Default)]
pub struct FrameCounters {
    frames: AtomicU64,
    incomplete: AtomicU64,
    dropped: AtomicU64,
}

impl FrameCounters {
    /// Counts a frame handed to the loop.
    pub fn frame(&self) {
        self.frames.fetch_add(1, Ordering::Relaxed);
    }

    /// Counts a frame that arrived incomplete or malformed.
    pub fn incomplete(&self) {
        self.incomplete.fetch_add(1, Ordering::Relaxed);
    }

    /// Counts `n` frames asked of the camera (by a trigger) that never
    /// arrived.
    pub fn dropped(&self, n: u64) {
        self.dropped.fetch_add(n, Ordering::Relaxed);
    }

    /// Frames handed to the loop, incomplete frames, dropped frames.
    pub fn read(&self) -> [u64; 3] {
        [&self.frames, &self.incomplete, &self.dropped].map(|c| c.load(Ordering::Relaxed))
    }
}
