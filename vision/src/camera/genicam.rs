//! GenICam cameras (GigE Vision and USB3 Vision: Basler, FLIR/Teledyne,
//! Allied Vision, IDS and most scientific CMOS cameras) through Aravis.
//! The settings ([`GenicamConfig`]) are always here; the camera itself
//! ([`GenicamCamera`], [`discover`], [`describe`]) needs the `aravis`
//! feature and Debian's libaravis-dev, so that the default build needs no
//! system package.

#[cfg(feature = "aravis")]
mod aravis_camera;

#[cfg(feature = "aravis")]
pub use aravis_camera::{GenicamCamera, describe, discover};

use serde::{Deserialize, Serialize};
use tweezer_config::{ConfigError, in_range};

/// Whether this build can drive GenICam cameras.
pub const AVAILABLE: bool = cfg!(feature = "aravis");

/// What to do in a build without GenICam support.
pub const REBUILD_HINT: &str = "this build has no GenICam support: install Debian's libaravis-dev and build with `cargo build --release --features tweezer-hardware-agent/aravis`";

/// The `[camera.genicam]` table: which camera, and how it acquires.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GenicamConfig {
    /// The camera: its id as `hardware-agent cameras` lists it, its serial
    /// number, or its IP address (a camera on another subnet, or on
    /// loopback, where discovery does not reach); empty: the first found.
    pub camera: String,
    /// The pixel format the camera sends.
    pub pixel_format: PixelFormat,
    /// Exposure time, µs; the camera's own when unset.
    pub exposure_us: Option<f64>,
    /// Analogue gain in the camera's units; the camera's own when unset.
    pub gain: Option<f64>,
    /// Region of interest `[x, y, width, height]`, px after binning; the
    /// camera's own when unset.
    pub roi: Option<[u32; 4]>,
    /// Horizontal and vertical binning; the camera's own when unset.
    pub binning: Option<[u32; 2]>,
    /// Free-run frame rate, Hz; the camera's own when unset. At least the
    /// control rate: each step waits for the next frame.
    pub frame_rate_hz: Option<f64>,
    /// How frames are started.
    pub acquisition: Acquisition,
    /// Frame buffers queued for the camera to fill.
    pub buffers: u32,
}

impl Default for GenicamConfig {
    fn default() -> Self {
        Self {
            camera: String::new(),
            pixel_format: PixelFormat::Mono8,
            exposure_us: None,
            gain: None,
            roi: None,
            binning: None,
            frame_rate_hz: None,
            acquisition: Acquisition::FreeRun,
            buffers: 8,
        }
    }
}

impl GenicamConfig {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), ConfigError> {
        for (name, value, lo, hi) in [
            ("exposure_us", self.exposure_us, 1.0, 1e8),
            ("gain", self.gain, -1e3, 1e3),
            ("frame_rate_hz", self.frame_rate_hz, 0.01, 1e5),
        ] {
            if let Some(value) = value {
                in_range(name, value, lo, hi)?;
            }
        }
        if let Some([_, _, w, h]) = self.roi
            && (w == 0 || h == 0)
        {
            return Err(ConfigError::invalid(
                "roi",
                format!("width and height must be positive, not {w} x {h}"),
            ));
        }
        if let Some(binning) = self.binning
            && binning.iter().any(|&b| !(1..=64).contains(&b))
        {
            return Err(ConfigError::invalid(
                "binning",
                format!("{binning:?}: each must lie in [1, 64]"),
            ));
        }
        if !(2..=256).contains(&self.buffers) {
            return Err(ConfigError::invalid(
                "buffers",
                format!("{} must lie in [2, 256]", self.buffers),
            ));
        }
        Ok(())
    }
}

/// The monochrome pixel formats the agent reads (PFNC names); 10- to
/// 16-bit pixels come unpacked, in two bytes, little-endian.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum PixelFormat {
    /// 8 bits.
    Mono8,
    /// 10 bits in 16.
    Mono10,
    /// 12 bits in 16.
    Mono12,
    /// 16 bits.
    Mono16,
}

impl PixelFormat {
    /// The PFNC name, as the camera lists it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Mono8 => "Mono8",
            Self::Mono10 => "Mono10",
            Self::Mono12 => "Mono12",
            Self::Mono16 => "Mono16",
        }
    }

    /// The largest pixel value.
    pub fn max_value(self) -> u16 {
        match self {
            Self::Mono8 => 255,
            Self::Mono10 => 1023,
            Self::Mono12 => 4095,
            Self::Mono16 => u16::MAX,
        }
    }

    /// Bytes per pixel.
    pub fn bytes(self) -> usize {
        match self {
            Self::Mono8 => 1,
            _ => 2,
        }
    }

    /// The frame in `data`, rows `stride` bytes apart; `None` when `data` is
    /// too short or a pixel exceeds the format's range (a corrupted buffer).
    pub fn frame(
        self,
        data: &[u8],
        [width, height]: [usize; 2],
        stride: usize,
    ) -> Option<super::GrayFrame> {
        let row = width * self.bytes();
        if stride < row || data.len() < stride * (height.max(1) - 1) + row {
            return None;
        }
        let mut pixels = Vec::with_capacity(width * height);
        for y in 0..height {
            let line = &data[y * stride..y * stride + row];
            match self {
                Self::Mono8 => pixels.extend(line.iter().map(|&v| u16::from(v))),
                _ => pixels.extend(
                    line.chunks_exact(2)
                        .map(|b| u16::from_le_bytes([b[0], b[1]])),
                ),
            }
        }
        super::GrayFrame::new(width, height, self.max_value(), pixels)
    }
}

/// How frames are started.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Acquisition {
    /// The camera runs at its frame rate; each step takes the first frame
    /// that arrives after it begins (the lower latency on the cameras
    /// measured, docs/hardware-agent.md).
    FreeRun,
    /// Each step triggers one exposure by software and waits for it.
    SoftwareTrigger,
}

/// A camera found on the network or the USB bus.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CameraInfo {
    /// The id to name it by in `camera.genicam.camera`.
    pub id: String,
    /// Its maker.
    pub vendor: String,
    /// Its model.
    pub model: String,
    /// Its serial number.
    pub serial: String,
    /// Its address (IP for GigE Vision).
    pub address: String,
    /// GigEVision or USB3Vision.
    pub protocol: String,
    /// The pixel formats it offers; empty if it could not be opened (in
    /// use by another program, say).
    pub pixel_formats: Vec<String>,
}

/// The settings a camera took, read back from it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GenicamSettings {
    /// Its id.
    pub id: String,
    /// Its model.
    pub model: String,
    /// The pixel format.
    pub pixel_format: String,
    /// Region of interest `[x, y, width, height]`.
    pub roi: [u32; 4],
    /// Binning.
    pub binning: Option<[u32; 2]>,
    /// Exposure, µs.
    pub exposure_us: Option<f64>,
    /// Gain.
    pub gain: Option<f64>,
    /// Free-run frame rate, Hz.
    pub frame_rate_hz: Option<f64>,
    /// How frames are started.
    pub acquisition: Acquisition,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wide_pixels_are_little_endian_and_rows_skip_their_padding() {
        let data = [1, 0, 0, 1, 9, 9, 255, 15, 2, 0, 9, 9];
        let frame = PixelFormat::Mono12.frame(&data, [2, 2], 6).unwrap();
        assert_eq!(frame.pixels(), &[1, 256, 4095, 2]);
        assert_eq!(frame.max_value(), 4095);
        // A 12-bit pixel above 4095 is a corrupted buffer.
        assert!(PixelFormat::Mono12.frame(&[0, 16], [1, 1], 2).is_none());
        assert!(PixelFormat::Mono8.frame(&[1, 2, 3], [2, 2], 2).is_none());
        let mono8 = PixelFormat::Mono8.frame(&[1, 2, 3, 4], [2, 2], 2).unwrap();
        assert_eq!(mono8.pixels(), &[1, 2, 3, 4]);
    }

    #[test]
    fn settings_out_of_range_are_named() {
        let bad = GenicamConfig {
            buffers: 1,
            ..GenicamConfig::default()
        };
        assert!(bad.validate().unwrap_err().to_string().contains("buffers"));
        let bad = GenicamConfig {
            exposure_us: Some(-3.0),
            ..GenicamConfig::default()
        };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("exposure_us")
        );
        let bad = GenicamConfig {
            roi: Some([0, 0, 0, 10]),
            ..GenicamConfig::default()
        };
        assert!(bad.validate().unwrap_err().to_string().contains("roi"));
        assert!(GenicamConfig::default().validate().is_ok());
    }
}
