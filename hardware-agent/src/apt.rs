//! The Thorlabs APT binary protocol as a KDC101 speaks it: message framing
//! (`frame`), the messages the stage driver sends and the replies it reads
//! (`message`), device units for Z8-series actuators (`units`), and a
//! simulated controller for the digital twin (`controller`).

mod controller;
mod frame;
mod message;
mod units;

pub use controller::{ActuatorModel, SimulatedController};
pub use frame::{AptError, Frame, FrameReader, HEADER_LEN};
pub use message::{
    Channel, Command, DcStatus, Direction, HardwareInfo, Reply, StopMode, VelocityParams,
};
pub use units::Z8Units;

/// The host's address in APT headers.
pub const HOST: u8 = 0x01;
/// The address of a single-channel USB controller such as the KDC101.
pub const DEVICE: u8 = 0x50;
