//! Seeing the microscope: grayscale camera frames and the [`Camera`] trait
//! a control loop grabs them through, frames read from and written to PNG
//! and TIFF files ([`ReplayCamera`] replays a directory), GenICam cameras
//! through Aravis ([`genicam`], with the `aravis` feature), and the
//! segmentation that finds sphere centres in a frame ([`Segmenter`]), as
//! `docs/spec.md` describes.

mod camera;
mod segment;

pub use camera::{
    Camera, CameraError, FrameCounters, GrayFrame, ReplayCamera, frame_stream, genicam, read_frame,
    write_frame,
};
pub use segment::{Detection, SegmentConfig, SegmentError, Segmenter};
