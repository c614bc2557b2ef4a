//! The Thorlabs APT binary protocol as a KDC101 speaks it: message framing
//! (`frame`), the messages the axis driver sends and the replies it reads
//! (`message`), and device units for Z8-series actuators (`units`).

mod frame;
mod message;
mod units;

pub use frame::{AptError, Frame, FrameReader, HEADER_LEN};
pub use message::{
    Channel, Command, DcStatus, Direction, HardwareInfo, HomeParams, JogParams, Param, Reply,
    StopMode, VelocityParams,
};
pub use units::Z8Units;

/// The host's address in APT headers.
pub const HOST: u8 = 0x01;
/// The address of a single-channel USB controller such as the KDC101.
pub const DEVICE: u8 = 0x50;
