//! The messages the stage driver sends to a KDC101 and the replies it
//! understands, with their ids and data layouts from Thorlabs' APT
//! communications protocol.

use super::frame::{AptError, Frame};
use super::{DEVICE, HOST};

const HW_REQ_INFO: u16 = 0x0005;
const HW_GET_INFO: u16 = 0x0006;
const HW_START_UPDATEMSGS: u16 = 0x0011;
const HW_STOP_UPDATEMSGS: u16 = 0x0012;
const HW_RESPONSE: u16 = 0x0080;
const HW_RICHRESPONSE: u16 = 0x0081;
const MOD_SET_CHANENABLESTATE: u16 = 0x0210;
const MOD_REQ_CHANENABLESTATE: u16 = 0x0211;
const MOD_GET_CHANENABLESTATE: u16 = 0x0212;
const MOT_REQ_POSCOUNTER: u16 = 0x0411;
const MOT_GET_POSCOUNTER: u16 = 0x0412;
const MOT_SET_VELPARAMS: u16 = 0x0413;
const MOT_REQ_VELPARAMS: u16 = 0x0414;
const MOT_GET_VELPARAMS: u16 = 0x0415;
const MOT_MOVE_VELOCITY: u16 = 0x0457;
const MOT_MOVE_COMPLETED: u16 = 0x0464;
const MOT_MOVE_STOP: u16 = 0x0465;
const MOT_MOVE_STOPPED: u16 = 0x0466;
const MOT_REQ_DCSTATUSUPDATE: u16 = 0x0490;
const MOT_GET_DCSTATUSUPDATE: u16 = 0x0491;
const MOT_ACK_DCSTATUSUPDATE: u16 = 0x0492;

/// A controller channel (the KDC101 has one: 1).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Channel(pub u8);

/// Direction of a velocity move.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    /// Increasing position.
    Forward,
    /// Decreasing position.
    Reverse,
}

/// How to stop.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StopMode {
    /// At once.
    Immediate,
    /// Decelerating with the velocity profile.
    Profiled,
}

/// Velocity profile in device units.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct VelocityParams {
    /// Start velocity (0 on DC servos).
    pub min_velocity: i32,
    /// Acceleration.
    pub acceleration: i32,
    /// Velocity of moves.
    pub max_velocity: i32,
}

impl VelocityParams {
    /// The data packet of MOT_SET_VELPARAMS / MOT_GET_VELPARAMS.
    fn data(&self, Channel(c): Channel) -> Vec<u8> {
        let mut data = u16::from(c).to_le_bytes().to_vec();
        for value in [self.min_velocity, self.acceleration, self.max_velocity] {
            data.extend_from_slice(&value.to_le_bytes());
        }
        data
    }
}

/// What the driver sends.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Command {
    /// HW_REQ_INFO: identify the controller.
    RequestInfo,
    /// HW_START_UPDATEMSGS: status updates every 100 ms.
    StartUpdates,
    /// HW_STOP_UPDATEMSGS.
    StopUpdates,
    /// MOD_SET_CHANENABLESTATE.
    Enable(Channel, bool),
    /// MOD_REQ_CHANENABLESTATE.
    RequestEnabled(Channel),
    /// MOT_SET_VELPARAMS.
    SetVelocity(Channel, VelocityParams),
    /// MOT_REQ_VELPARAMS.
    RequestVelocity(Channel),
    /// MOT_MOVE_VELOCITY: move until stopped, at the profile's velocity.
    MoveVelocity(Channel, Direction),
    /// MOT_MOVE_STOP.
    Stop(Channel, StopMode),
    /// MOT_REQ_POSCOUNTER.
    RequestPosition(Channel),
    /// MOT_REQ_DCSTATUSUPDATE.
    RequestStatus(Channel),
    /// MOT_ACK_DCSTATUSUPDATE: keeps status updates flowing.
    AckStatus,
}

/// The controller's identity (HW_GET_INFO).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct HardwareInfo {
    /// Serial number (KDC101s start with 27).
    pub serial: u32,
    /// Model, e.g. `KDC101`.
    pub model: String,
    /// Firmware version, `major.interim.minor`.
    pub firmware: String,
    /// Hardware version.
    pub hardware_version: u16,
    /// Channels.
    pub channels: u16,
}

/// A status update (MOT_GET_DCSTATUSUPDATE, MOVE_COMPLETED, MOVE_STOPPED).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DcStatus {
    /// The channel.
    pub channel: Channel,
    /// Position counter, encoder counts.
    pub position: i32,
    /// Velocity as the status word carries it (informational).
    pub velocity: u16,
    /// Status bits (limit switches, moving, homed, errors, enabled).
    pub bits: u32,
}

impl DcStatus {
    /// Forward or reverse hardware limit switch active.
    pub fn at_limit(&self) -> bool {
        self.bits & 0b11 != 0
    }

    /// Moving in either direction (bits 4–7).
    pub fn moving(&self) -> bool {
        self.bits & 0xf0 != 0
    }

    /// Channel enabled (bit 31).
    pub fn enabled(&self) -> bool {
        self.bits & 0x8000_0000 != 0
    }
}

/// What the driver understands from the controller.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Reply {
    /// HW_GET_INFO.
    Info(HardwareInfo),
    /// MOD_GET_CHANENABLESTATE.
    Enabled(Channel, bool),
    /// MOT_GET_VELPARAMS.
    Velocity(Channel, VelocityParams),
    /// MOT_GET_POSCOUNTER.
    Position(Channel, i32),
    /// MOT_GET_DCSTATUSUPDATE.
    Status(DcStatus),
    /// MOT_MOVE_COMPLETED.
    MoveCompleted(DcStatus),
    /// MOT_MOVE_STOPPED.
    MoveStopped(DcStatus),
}

impl Reply {
    /// The channel the reply is about, when it is about one.
    pub fn channel(&self) -> Option<Channel> {
        match self {
            Self::Info(_) => None,
            Self::Enabled(channel, _) | Self::Velocity(channel, _) | Self::Position(channel, _) => {
                Some(*channel)
            }
            Self::Status(status) | Self::MoveCompleted(status) | Self::MoveStopped(status) => {
                Some(status.channel)
            }
        }
    }
}

impl Command {
    /// The frame to send to the controller at `DEVICE`.
    pub fn to_frame(self) -> Frame {
        let short = |id: u16, param1: u8, param2: u8| Frame::Short {
            id,
            param1,
            param2,
            dest: DEVICE,
            source: HOST,
        };
        match self {
            Self::RequestInfo => short(HW_REQ_INFO, 0, 0),
            Self::StartUpdates => short(HW_START_UPDATEMSGS, 0, 0),
            Self::StopUpdates => short(HW_STOP_UPDATEMSGS, 0, 0),
            Self::Enable(Channel(c), on) => {
                short(MOD_SET_CHANENABLESTATE, c, if on { 1 } else { 2 })
            }
            Self::RequestEnabled(Channel(c)) => short(MOD_REQ_CHANENABLESTATE, c, 0),
            Self::SetVelocity(channel, p) => Frame::Long {
                id: MOT_SET_VELPARAMS,
                dest: DEVICE,
                source: HOST,
                data: p.data(channel),
            },
            Self::RequestVelocity(Channel(c)) => short(MOT_REQ_VELPARAMS, c, 0),
            Self::MoveVelocity(Channel(c), direction) => short(
                MOT_MOVE_VELOCITY,
                c,
                match direction {
                    Direction::Forward => 1,
                    Direction::Reverse => 2,
                },
            ),
            Self::Stop(Channel(c), mode) => short(
                MOT_MOVE_STOP,
                c,
                match mode {
                    StopMode::Immediate => 1,
                    StopMode::Profiled => 2,
                },
            ),
            Self::RequestPosition(Channel(c)) => short(MOT_REQ_POSCOUNTER, c, 0),
            Self::RequestStatus(Channel(c)) => short(MOT_REQ_DCSTATUSUPDATE, c, 0),
            Self::AckStatus => short(MOT_ACK_DCSTATUSUPDATE, 0, 0),
        }
    }
}

impl Command {
    /// The command a frame from the host carries (the simulated
    /// controller's side).
    pub fn from_frame(frame: &Frame) -> Result<Self, AptError> {
        let on_off = |p: u8, what: &str| match p {
            1 => Ok(true),
            2 => Ok(false),
            other => Err(AptError::Unexpected(format!("{what} parameter {other}"))),
        };
        match frame {
            Frame::Short {
                id, param1, param2, ..
            } => {
                let c = Channel(*param1);
                Ok(match *id {
                    HW_REQ_INFO => Self::RequestInfo,
                    HW_START_UPDATEMSGS => Self::StartUpdates,
                    HW_STOP_UPDATEMSGS => Self::StopUpdates,
                    MOT_ACK_DCSTATUSUPDATE => Self::AckStatus,
                    MOD_SET_CHANENABLESTATE => Self::Enable(c, on_off(*param2, "enable state")?),
                    MOD_REQ_CHANENABLESTATE => Self::RequestEnabled(c),
                    MOT_REQ_VELPARAMS => Self::RequestVelocity(c),
                    MOT_MOVE_VELOCITY => Self::MoveVelocity(
                        c,
                        if on_off(*param2, "direction")? {
                            Direction::Forward
                        } else {
                            Direction::Reverse
                        },
                    ),
                    MOT_MOVE_STOP => Self::Stop(
                        c,
                        if on_off(*param2, "stop mode")? {
                            StopMode::Immediate
                        } else {
                            StopMode::Profiled
                        },
                    ),
                    MOT_REQ_POSCOUNTER => Self::RequestPosition(c),
                    MOT_REQ_DCSTATUSUPDATE => Self::RequestStatus(c),
                    other => {
                        return Err(AptError::Unexpected(format!("command 0x{other:04x}")));
                    }
                })
            }
            Frame::Long { id, data, .. } if *id == MOT_SET_VELPARAMS => {
                let (channel, params) = Fields::of(*id, data, 14)?.velocity_params();
                Ok(Self::SetVelocity(channel, params))
            }
            Frame::Long { id, data, .. } => Err(AptError::Unexpected(format!(
                "command 0x{id:04x} with {} data bytes",
                data.len()
            ))),
        }
    }
}

/// Little-endian fields of a data packet, checked for length up front.
struct Fields<'a> {
    data: &'a [u8],
    at: usize,
}

impl<'a> Fields<'a> {
    fn of(id: u16, data: &'a [u8], expected: usize) -> Result<Self, AptError> {
        if data.len() != expected {
            return Err(AptError::Length {
                id,
                got: data.len(),
                expected,
            });
        }
        Ok(Self { data, at: 0 })
    }

    fn take<const N: usize>(&mut self) -> [u8; N] {
        let bytes: [u8; N] = self.data[self.at..self.at + N]
            .try_into()
            .expect("length checked in Fields::of");
        self.at += N;
        bytes
    }

    fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.take())
    }

    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }

    fn i32(&mut self) -> i32 {
        i32::from_le_bytes(self.take())
    }

    fn text<const N: usize>(&mut self) -> String {
        let bytes: [u8; N] = self.take();
        let end = bytes.iter().position(|&b| b == 0).unwrap_or(N);
        String::from_utf8_lossy(&bytes[..end]).trim().to_string()
    }

    fn velocity_params(&mut self) -> (Channel, VelocityParams) {
        let channel = Channel(self.u16() as u8);
        let params = VelocityParams {
            min_velocity: self.i32(),
            acceleration: self.i32(),
            max_velocity: self.i32(),
        };
        (channel, params)
    }

    fn status(&mut self) -> DcStatus {
        DcStatus {
            channel: Channel(self.u16() as u8),
            position: self.i32(),
            velocity: self.u16(),
            bits: {
                let _reserved = self.u16();
                self.u32()
            },
        }
    }
}

impl Reply {
    /// The reply a frame carries; a controller error report is
    /// [`AptError::Device`], anything else unknown [`AptError::Unexpected`].
    pub fn from_frame(frame: &Frame) -> Result<Self, AptError> {
        match frame {
            Frame::Short {
                id: MOD_GET_CHANENABLESTATE,
                param1,
                param2,
                ..
            } => Ok(Self::Enabled(Channel(*param1), *param2 == 1)),
            // HW_RESPONSE is header-only: a fault that needs attention.
            Frame::Short {
                id: HW_RESPONSE,
                param1,
                param2,
                ..
            } => Err(AptError::Device {
                code: u16::from_le_bytes([*param1, *param2]),
                text: "a fault that needs attention (HW_RESPONSE)".into(),
            }),
            Frame::Long { id, data, .. } => Self::from_data(*id, data),
            Frame::Short {
                id, param1, param2, ..
            } => Err(AptError::Unexpected(format!(
                "message 0x{id:04x} (parameters {param1}, {param2})"
            ))),
        }
    }

    fn from_data(id: u16, data: &[u8]) -> Result<Self, AptError> {
        match id {
            HW_GET_INFO => {
                let mut f = Fields::of(id, data, 84)?;
                let serial = f.u32();
                let model = f.text::<8>();
                let _kind = f.u16();
                let [minor, interim, major, _] = f.take::<4>();
                let _notes = f.take::<48>();
                let _empty = f.take::<12>();
                let hardware_version = f.u16();
                let _modification = f.u16();
                let channels = f.u16();
                Ok(Self::Info(HardwareInfo {
                    serial,
                    model,
                    firmware: format!("{major}.{interim}.{minor}"),
                    hardware_version,
                    channels,
                }))
            }
            MOT_GET_VELPARAMS => {
                let (channel, params) = Fields::of(id, data, 14)?.velocity_params();
                Ok(Self::Velocity(channel, params))
            }
            MOT_GET_POSCOUNTER => {
                let mut f = Fields::of(id, data, 6)?;
                let channel = Channel(f.u16() as u8);
                Ok(Self::Position(channel, f.i32()))
            }
            MOT_GET_DCSTATUSUPDATE => Ok(Self::Status(Fields::of(id, data, 14)?.status())),
            MOT_MOVE_COMPLETED => Ok(Self::MoveCompleted(Fields::of(id, data, 14)?.status())),
            MOT_MOVE_STOPPED => Ok(Self::MoveStopped(Fields::of(id, data, 14)?.status())),
            HW_RICHRESPONSE => {
                let mut f = Fields::of(id, data, 68)?;
                let _message = f.u16();
                let code = f.u16();
                Err(AptError::Device {
                    code,
                    text: f.text::<64>(),
                })
            }
            _ => Err(AptError::Unexpected(format!(
                "message 0x{id:04x} with {} data bytes",
                data.len()
            ))),
        }
    }

    /// The frame a controller sends for this reply (the simulated
    /// controller's side).
    pub fn to_frame(&self) -> Frame {
        let long = |id: u16, data: Vec<u8>| Frame::Long {
            id,
            dest: HOST,
            source: DEVICE,
            data,
        };
        let status = |id: u16, s: &DcStatus| {
            let mut data = u16::from(s.channel.0).to_le_bytes().to_vec();
            data.extend_from_slice(&s.position.to_le_bytes());
            data.extend_from_slice(&s.velocity.to_le_bytes());
            data.extend_from_slice(&0u16.to_le_bytes());
            data.extend_from_slice(&s.bits.to_le_bytes());
            long(id, data)
        };
        match self {
            Self::Info(info) => {
                let mut data = info.serial.to_le_bytes().to_vec();
                let mut model = [0u8; 8];
                for (slot, byte) in model.iter_mut().zip(info.model.bytes()) {
                    *slot = byte;
                }
                data.extend_from_slice(&model);
                data.extend_from_slice(&0u16.to_le_bytes());
                let version: Vec<u8> = info
                    .firmware
                    .split('.')
                    .rev()
                    .map(|p| p.parse().unwrap_or(0))
                    .chain(std::iter::repeat(0))
                    .take(4)
                    .collect();
                data.extend_from_slice(&version);
                data.extend_from_slice(&[0u8; 60]);
                data.extend_from_slice(&info.hardware_version.to_le_bytes());
                data.extend_from_slice(&0u16.to_le_bytes());
                data.extend_from_slice(&info.channels.to_le_bytes());
                long(HW_GET_INFO, data)
            }
            Self::Enabled(Channel(c), on) => Frame::Short {
                id: MOD_GET_CHANENABLESTATE,
                param1: *c,
                param2: if *on { 1 } else { 2 },
                dest: HOST,
                source: DEVICE,
            },
            Self::Velocity(channel, p) => long(MOT_GET_VELPARAMS, p.data(*channel)),
            Self::Position(Channel(c), position) => {
                let mut data = u16::from(*c).to_le_bytes().to_vec();
                data.extend_from_slice(&position.to_le_bytes());
                long(MOT_GET_POSCOUNTER, data)
            }
            Self::Status(s) => status(MOT_GET_DCSTATUSUPDATE, s),
            Self::MoveCompleted(s) => status(MOT_MOVE_COMPLETED, s),
            Self::MoveStopped(s) => status(MOT_MOVE_STOPPED, s),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CH: Channel = Channel(1);

    #[test]
    fn commands_have_the_protocol_bytes() {
        let bytes = |c: Command| c.to_frame().encode();
        assert_eq!(bytes(Command::RequestInfo), [0x05, 0x00, 0, 0, 0x50, 0x01]);
        assert_eq!(
            bytes(Command::Enable(CH, true)),
            [0x10, 0x02, 1, 1, 0x50, 0x01]
        );
        assert_eq!(
            bytes(Command::MoveVelocity(CH, Direction::Reverse)),
            [0x57, 0x04, 1, 2, 0x50, 0x01]
        );
        assert_eq!(
            bytes(Command::Stop(CH, StopMode::Immediate)),
            [0x65, 0x04, 1, 1, 0x50, 0x01]
        );
        let set = bytes(Command::SetVelocity(
            CH,
            VelocityParams {
                min_velocity: 0,
                acceleration: 0x0102,
                max_velocity: -2,
            },
        ));
        assert_eq!(
            set,
            [
                0x13, 0x04, 14, 0, 0xd0, 0x01, 1, 0, 0, 0, 0, 0, 2, 1, 0, 0, 0xfe, 0xff, 0xff, 0xff
            ]
        );
    }

    #[test]
    fn commands_round_trip_through_frames() {
        let params = VelocityParams {
            min_velocity: 0,
            acceleration: 264,
            max_velocity: 772_981,
        };
        for command in [
            Command::RequestInfo,
            Command::StartUpdates,
            Command::StopUpdates,
            Command::Enable(CH, false),
            Command::RequestEnabled(CH),
            Command::SetVelocity(CH, params),
            Command::RequestVelocity(CH),
            Command::MoveVelocity(CH, Direction::Forward),
            Command::Stop(CH, StopMode::Profiled),
            Command::RequestPosition(CH),
            Command::RequestStatus(CH),
            Command::AckStatus,
        ] {
            assert_eq!(Command::from_frame(&command.to_frame()).unwrap(), command);
        }
    }

    #[test]
    fn replies_round_trip_through_frames() {
        let status = DcStatus {
            channel: CH,
            position: -123_456,
            velocity: 7,
            bits: 0x8000_0010,
        };
        assert!(status.enabled() && status.moving() && !status.at_limit());
        for reply in [
            Reply::Info(HardwareInfo {
                serial: 27_000_001,
                model: "KDC101".into(),
                firmware: "3.0.10".into(),
                hardware_version: 1,
                channels: 1,
            }),
            Reply::Enabled(CH, true),
            Reply::Velocity(
                CH,
                VelocityParams {
                    min_velocity: 0,
                    acceleration: 4_506,
                    max_velocity: 1_649_852,
                },
            ),
            Reply::Position(CH, 40_000),
            Reply::Status(status),
            Reply::MoveCompleted(status),
            Reply::MoveStopped(status),
        ] {
            assert_eq!(Reply::from_frame(&reply.to_frame()).unwrap(), reply);
        }
    }

    #[test]
    fn malformed_and_unknown_replies_are_errors() {
        let short_status = Frame::Long {
            id: MOT_GET_DCSTATUSUPDATE,
            dest: HOST,
            source: DEVICE,
            data: vec![0; 10],
        };
        let err = Reply::from_frame(&short_status).unwrap_err();
        assert!(
            matches!(
                err,
                AptError::Length {
                    got: 10,
                    expected: 14,
                    ..
                }
            ),
            "{err}"
        );
        let unknown = Frame::Short {
            id: 0x0999,
            param1: 0,
            param2: 0,
            dest: HOST,
            source: DEVICE,
        };
        assert!(
            Reply::from_frame(&unknown)
                .unwrap_err()
                .to_string()
                .contains("0x0999")
        );
        let mut data = vec![0x57, 0x04, 0x2a, 0x00];
        let mut text = [0u8; 64];
        text[..13].copy_from_slice(b"limit reached");
        data.extend_from_slice(&text);
        let device = Frame::Long {
            id: HW_RICHRESPONSE,
            dest: HOST,
            source: DEVICE,
            data,
        };
        let err = Reply::from_frame(&device).unwrap_err();
        assert!(
            matches!(&err, AptError::Device { code: 42, text } if text == "limit reached"),
            "{err}"
        );
    }

    #[test]
    fn a_header_only_hw_response_is_the_controller_reporting_a_fault() {
        // 80 00 00 00 01 50, as the APT documentation gives it: six bytes,
        // no data packet.
        let bytes = [0x80, 0x00, 0x00, 0x00, HOST, DEVICE];
        let frame = crate::apt::FrameReader::new(&bytes[..])
            .read_frame()
            .unwrap();
        let err = Reply::from_frame(&frame).unwrap_err();
        assert!(
            matches!(&err, AptError::Device { code: 0, text } if text.contains("HW_RESPONSE")),
            "{err}"
        );
    }

    #[test]
    fn a_reply_names_its_channel() {
        let position = Reply::Position(Channel(2), 5);
        assert_eq!(position.channel(), Some(Channel(2)));
        let info = Reply::Info(HardwareInfo {
            serial: 1,
            model: "KDC101".into(),
            firmware: "1.0.0".into(),
            hardware_version: 1,
            channels: 1,
        });
        assert_eq!(info.channel(), None);
    }
}
