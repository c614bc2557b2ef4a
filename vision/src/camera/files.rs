//! Frames as image files: PNG or TIFF, 8- or 16-bit grayscale (colour
//! files are converted to gray).

use super::{CameraError, GrayFrame};
use image::{DynamicImage, ImageBuffer, ImageReader, Luma};
use std::path::Path;

/// Reads a PNG or TIFF frame.
pub fn read_frame(path: &Path) -> Result<GrayFrame, CameraError> {
    let error = |reason: String| CameraError::Read {
        path: path.to_path_buf(),
        reason,
    };
    let image = ImageReader::open(path)
        .map_err(|e| error(e.to_string()))?
        .with_guessed_format()
        .map_err(|e| error(e.to_string()))?
        .decode()
        .map_err(|e| error(e.to_string()))?;
    let (width, height) = (image.width() as usize, image.height() as usize);
    let (max_value, pixels) = match image {
        DynamicImage::ImageLuma8(gray) => {
            (255, gray.into_raw().into_iter().map(u16::from).collect())
        }
        DynamicImage::ImageLuma16(gray) => (u16::MAX, gray.into_raw()),
        other if other.color().bytes_per_pixel() / other.color().channel_count() >= 2 => {
            (u16::MAX, other.to_luma16().into_raw())
        }
        other => (
            255,
            other
                .to_luma8()
                .into_raw()
                .into_iter()
                .map(u16::from)
                .collect(),
        ),
    };
    GrayFrame::new(width, height, max_value, pixels).ok_or_else(|| error("empty image".into()))
}

/// Writes a frame as PNG or TIFF (by the file's extension): 8-bit when its
/// values fit, else 16-bit.
pub fn write_frame(path: &Path, frame: &GrayFrame) -> Result<(), CameraError> {
    let error = |reason: String| CameraError::Write {
        path: path.to_path_buf(),
        reason,
    };
    let (w, h) = (frame.width() as u32, frame.height() as u32);
    let saved = if frame.max_value() <= 255 {
        let bytes = frame.pixels().iter().map(|&p| p as u8).collect();
        ImageBuffer::<Luma<u8>, Vec<u8>>::from_raw(w, h, bytes)
            .expect("a frame's pixel count matches its size")
            .save(path)
    } else {
        ImageBuffer::<Luma<u16>, Vec<u16>>::from_raw(w, h, frame.pixels().to_vec())
            .expect("a frame's pixel count matches its size")
            .save(path)
    };
    saved.map_err(|e| error(e.to_string()))
}
