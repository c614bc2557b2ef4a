//! APT framing: a 6-byte header (message id, two parameter bytes or a data
//! length, destination, source), followed by a data packet when the
//! destination byte has its top bit set. Little-endian throughout.

use std::io::Read;

/// Bytes in a header.
pub const HEADER_LEN: usize = 6;
/// The longest data packet any message we read carries (HW_GET_INFO: 84).
const MAX_DATA: usize = 255;

/// One message on the wire.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Frame {
    /// A header-only message with its two parameter bytes.
    Short {
        /// Message id.
        id: u16,
        /// First parameter byte.
        param1: u8,
        /// Second parameter byte.
        param2: u8,
        /// Destination address.
        dest: u8,
        /// Source address.
        source: u8,
    },
    /// A header followed by a data packet.
    Long {
        /// Message id.
        id: u16,
        /// Destination address (without the data flag).
        dest: u8,
        /// Source address.
        source: u8,
        /// The data packet.
        data: Vec<u8>,
    },
}

/// What can go wrong between the driver and a controller.
#[derive(Debug, thiserror::Error)]
pub enum AptError {
    /// The serial port failed or closed.
    #[error("serial I/O: {0}")]
    Io(#[from] std::io::Error),
    /// No (complete) reply in time.
    #[error("no reply from the controller within {0:?}")]
    Timeout(std::time::Duration),
    /// A header announcing more data than any message carries.
    #[error("message 0x{id:04x} announces {len} data bytes (at most {MAX_DATA})")]
    Oversized {
        /// Message id.
        id: u16,
        /// Announced length.
        len: usize,
    },
    /// A message that is not what the driver expects here.
    #[error("unexpected reply: {0}")]
    Unexpected(String),
    /// A known message with a data packet of the wrong size.
    #[error("message 0x{id:04x} carries {got} data bytes, expected {expected}")]
    Length {
        /// Message id.
        id: u16,
        /// Bytes received.
        got: usize,
        /// Bytes the message has.
        expected: usize,
    },
    /// The controller on the port is not the model the driver drives.
    #[error("the controller on this port is a {model:?}, not a KDC101")]
    Model {
        /// The model it reports (HW_GET_INFO).
        model: String,
    },
    /// The stage did not do what it was told, or its controller reported
    /// a fault in its status: the driver stopped it, and refuses every
    /// later move.
    #[error(
        "{0}. The motor was stopped and the driver moves it no more: check the stage, \
         then restart the agent"
    )]
    Untrusted(String),
    /// The controller reported an error (HW_RESPONSE / HW_RICHRESPONSE).
    #[error("the controller reports error {code}: {text}")]
    Device {
        /// The controller's error code.
        code: u16,
        /// Its description.
        text: String,
    },
}

impl Frame {
    /// The message id.
    pub fn id(&self) -> u16 {
        match self {
            Self::Short { id, .. } | Self::Long { id, .. } => *id,
        }
    }

    /// The addresses in the header: destination (without the data flag)
    /// and source.
    pub fn addresses(&self) -> (u8, u8) {
        match self {
            Self::Short { dest, source, .. } | Self::Long { dest, source, .. } => {
                (*dest & 0x7f, *source)
            }
        }
    }

    /// The bytes on the wire.
    pub fn encode(&self) -> Vec<u8> {
        match self {
            Self::Short {
                id,
                param1,
                param2,
                dest,
                source,
            } => {
                let [a, b] = id.to_le_bytes();
                vec![a, b, *param1, *param2, *dest & 0x7f, *source]
            }
            Self::Long {
                id,
                dest,
                source,
                data,
            } => {
                let [a, b] = id.to_le_bytes();
                let [l0, l1] = (data.len() as u16).to_le_bytes();
                let mut bytes = vec![a, b, l0, l1, *dest | 0x80, *source];
                bytes.extend_from_slice(data);
                bytes
            }
        }
    }
}

/// Reads whole frames from a byte stream, keeping a partial frame across
/// read timeouts.
#[derive(Debug)]
pub struct FrameReader<R> {
    inner: R,
    pending: Vec<u8>,
}

impl<R: Read> FrameReader<R> {
    /// Frames from `inner`.
    pub fn new(inner: R) -> Self {
        Self {
            inner,
            pending: Vec::with_capacity(HEADER_LEN + MAX_DATA),
        }
    }

    /// The next frame. A read timeout of the underlying stream surfaces as
    /// an I/O error of kind `TimedOut` or `WouldBlock`; the bytes of a frame
    /// not yet whole are kept for the next call.
    pub fn read_frame(&mut self) -> Result<Frame, AptError> {
        loop {
            if let Some(frame) = self.take_frame()? {
                return Ok(frame);
            }
            let mut chunk = [0u8; HEADER_LEN + MAX_DATA];
            let n = match self.inner.read(&mut chunk) {
                Ok(0) => {
                    return Err(AptError::Io(std::io::Error::new(
                        std::io::ErrorKind::UnexpectedEof,
                        "the port closed",
                    )));
                }
                Ok(n) => n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(e.into()),
            };
            self.pending.extend_from_slice(&chunk[..n]);
        }
    }

    /// The first whole frame of the pending bytes, removed from them.
    fn take_frame(&mut self) -> Result<Option<Frame>, AptError> {
        let Some(header) = self.pending.get(..HEADER_LEN) else {
            return Ok(None);
        };
        let id = u16::from_le_bytes([header[0], header[1]]);
        let (dest, source) = (header[4], header[5]);
        if dest & 0x80 == 0 {
            let frame = Frame::Short {
                id,
                param1: header[2],
                param2: header[3],
                dest,
                source,
            };
            self.pending.drain(..HEADER_LEN);
            return Ok(Some(frame));
        }
        let len = usize::from(u16::from_le_bytes([header[2], header[3]]));
        if len > MAX_DATA {
            // Nothing after a corrupt header can be trusted.
            self.pending.clear();
            return Err(AptError::Oversized { id, len });
        }
        if self.pending.len() < HEADER_LEN + len {
            return Ok(None);
        }
        let data = self.pending[HEADER_LEN..HEADER_LEN + len].to_vec();
        self.pending.drain(..HEADER_LEN + len);
        Ok(Some(Frame::Long {
            id,
            dest: dest & 0x7f,
            source,
            data,
        }))
    }

    /// Drops the bytes of a frame not yet whole (after an error: the rest
    /// of it may never come, and must not be read as the start of another).
    pub fn discard(&mut self) {
        self.pending.clear();
    }

    /// The underlying stream.
    pub fn get_mut(&mut self) -> &mut R {
        &mut self.inner
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_and_long_frames_round_trip() {
        let short = Frame::Short {
            id: 0x0457,
            param1: 0x01,
            param2: 0x02,
            dest: 0x50,
            source: 0x01,
        };
        assert_eq!(short.encode(), [0x57, 0x04, 0x01, 0x02, 0x50, 0x01]);
        let long = Frame::Long {
            id: 0x0413,
            dest: 0x50,
            source: 0x01,
            data: vec![1, 2, 3],
        };
        assert_eq!(long.encode(), [0x13, 0x04, 3, 0, 0xd0, 0x01, 1, 2, 3]);
        let mut bytes = short.encode();
        bytes.extend(long.encode());
        let mut reader = FrameReader::new(bytes.as_slice());
        assert_eq!(reader.read_frame().unwrap(), short);
        assert_eq!(reader.read_frame().unwrap(), long);
        assert!(matches!(reader.read_frame(), Err(AptError::Io(_))));
    }

    #[test]
    fn truncated_and_oversized_frames_are_errors() {
        let mut reader = FrameReader::new(&[0x13, 0x04, 3, 0, 0xd0, 0x01, 1][..]);
        assert!(matches!(reader.read_frame(), Err(AptError::Io(_))));
        let mut reader = FrameReader::new(&[0x13, 0x04, 0xff, 0xff, 0xd0, 0x01][..]);
        let err = reader.read_frame().unwrap_err();
        assert!(
            matches!(err, AptError::Oversized { len: 65535, .. }),
            "{err}"
        );
        assert!(err.to_string().contains("0x0413"));
    }
}
