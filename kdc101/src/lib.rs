//! Thorlabs KDC101 motor controllers driving Z8-series actuators, over the
//! APT serial protocol: the protocol's frames and messages ([`apt`]), the
//! serial port ([`open_port`]), a one-axis driver that keeps its stage
//! inside soft travel and speed limits ([`Axis`]), two such stages moved as
//! one in image coordinates through a calibration ([`StagePair`]), and a
//! simulated controller ([`SimulatedController`]) served on a
//! pseudo-terminal ([`PtySimulator`]) for tests and digital twins. Nothing
//! here knows about optical tweezers.

pub mod apt;
mod axis;
mod pty_simulator;
mod serial;
mod simulator;
mod stage_pair;

pub use axis::{Axis, AxisLimits, Commanded};
pub use pty_simulator::{ControllerGuard, Fault, PtySimulator};
pub use serial::open_port;
pub use simulator::{ActuatorModel, Malfunction, SimulatedController};
pub use stage_pair::{
    Calibration, ImageAxis, SharedPort, StagePair, StagesConfig, StagesError, Stopper,
};
