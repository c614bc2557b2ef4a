//! The KDC101's USB serial port: 115200 baud, 8N1, RTS/CTS flow control.

use serialport::{DataBits, FlowControl, Parity, StopBits, TTYPort};
use std::path::Path;
use std::time::Duration;

/// How long one read waits before the driver checks its own deadline.
const READ_POLL: Duration = Duration::from_millis(5);

/// Opens `path` as the APT protocol requires.
pub fn open_port(path: &Path) -> Result<TTYPort, serialport::Error> {
    serialport::new(path.to_string_lossy(), 115_200)
        .data_bits(DataBits::Eight)
        .parity(Parity::None)
        .stop_bits(StopBits::One)
        .flow_control(FlowControl::Hardware)
        .timeout(READ_POLL)
        .open_native()
}
