//! The messages a host sends to a KDC101 and the replies the controller
//! sends back, with their ids and data layouts from Thorlabs' APT
//! communications protocol: those the stage driver uses, and those a
//! KDC101 user's other software sends (homing, absolute, relative and jog
//! moves and their parameters), which the simulated controller answers.

use super::frame::{AptError, Frame};
use super::{DEVICE, HOST};

const HW_DISCONNECT: u16 = 0x0002;
const HW_REQ_INFO: u16 = 0x0005;
const HW_GET_INFO: u16 = 0x0006;
const HW_START_UPDATEMSGS: u16 = 0x0011;
const HW_STOP_UPDATEMSGS: u16 = 0x0012;
const HW_RESPONSE: u16 = 0x0080;
const HW_RICHRESPONSE: u16 = 0x0081;
const MOD_SET_CHANENABLESTATE: u16 = 0x0210;
const MOD_REQ_CHANENABLESTATE: u16 = 0x0211;
const MOD_GET_CHANENABLESTATE: u16 = 0x0212;
const MOD_IDENTIFY: u16 = 0x0223;
const MOT_SET_POSCOUNTER: u16 = 0x0410;
const MOT_REQ_POSCOUNTER: u16 = 0x0411;
const MOT_GET_POSCOUNTER: u16 = 0x0412;
const MOT_SET_VELPARAMS: u16 = 0x0413;
const MOT_REQ_VELPARAMS: u16 = 0x0414;
const MOT_GET_VELPARAMS: u16 = 0x0415;
const MOT_SET_JOGPARAMS: u16 = 0x0416;
const MOT_REQ_JOGPARAMS: u16 = 0x0417;
const MOT_GET_JOGPARAMS: u16 = 0x0418;
const MOT_REQ_STATUSBITS: u16 = 0x0429;
const MOT_GET_STATUSBITS: u16 = 0x042A;
const MOT_SET_HOMEPARAMS: u16 = 0x0440;
const MOT_REQ_HOMEPARAMS: u16 = 0x0441;
const MOT_GET_HOMEPARAMS: u16 = 0x0442;
const MOT_MOVE_HOME: u16 = 0x0443;
const MOT_MOVE_HOMED: u16 = 0x0444;
const MOT_MOVE_RELATIVE: u16 = 0x0448;
const MOT_MOVE_ABSOLUTE: u16 = 0x0453;
const MOT_MOVE_VELOCITY: u16 = 0x0457;
const MOT_MOVE_COMPLETED: u16 = 0x0464;
const MOT_MOVE_STOP: u16 = 0x0465;
const MOT_MOVE_STOPPED: u16 = 0x0466;
const MOT_MOVE_JOG: u16 = 0x046A;
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

/// A parameter that is one signed 32-bit value per channel, with its set,
/// request and get messages.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Param {
    /// MOT_*_GENMOVEPARAMS: the backlash distance, encoder counts.
    Backlash,
    /// MOT_*_MOVERELPARAMS: the distance of a relative move.
    RelativeDistance,
    /// MOT_*_MOVEABSPARAMS: the target of an absolute move.
    AbsolutePosition,
    /// MOT_*_ENCCOUNTER: the encoder counter.
    EncoderCount,
}

impl Param {
    const ALL: [Self; 4] = [
        Self::Backlash,
        Self::RelativeDistance,
        Self::AbsolutePosition,
        Self::EncoderCount,
    ];

    /// The (set, request, get) message ids.
    fn ids(self) -> (u16, u16, u16) {
        match self {
            Self::Backlash => (0x043A, 0x043B, 0x043C),
            Self::RelativeDistance => (0x0445, 0x0446, 0x0447),
            Self::AbsolutePosition => (0x0450, 0x0451, 0x0452),
            Self::EncoderCount => (0x0409, 0x040A, 0x040B),
        }
    }
}

/// Jog moves in device units (MOT_SET_JOGPARAMS).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct JogParams {
    /// 1: continuous while the button is held, 2: one step per jog.
    pub mode: u16,
    /// The step, encoder counts.
    pub step: i32,
    /// Start velocity.
    pub min_velocity: i32,
    /// Acceleration.
    pub acceleration: i32,
    /// Velocity.
    pub max_velocity: i32,
    /// 1: immediate, 2: profiled.
    pub stop_mode: u16,
}

/// Homing in device units (MOT_SET_HOMEPARAMS).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct HomeParams {
    /// 1: forward, 2: reverse.
    pub direction: u16,
    /// The limit switch homed on (1: reverse, 4: forward).
    pub limit_switch: u16,
    /// Velocity.
    pub velocity: i32,
    /// Distance from the limit switch to the home position, counts.
    pub offset: i32,
}

/// What a host sends.
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
    /// MOD_IDENTIFY: flash the front panel.
    Identify,
    /// HW_DISCONNECT: the host is going away.
    Disconnect,
    /// MOT_SET_POSCOUNTER: call the present position this count.
    SetPosition(Channel, i32),
    /// Sets a one-value parameter.
    SetParam(Channel, Param, i32),
    /// Asks for a one-value parameter.
    RequestParam(Channel, Param),
    /// MOT_SET_JOGPARAMS.
    SetJog(Channel, JogParams),
    /// MOT_REQ_JOGPARAMS.
    RequestJog(Channel),
    /// MOT_MOVE_JOG: one jog step (or, in continuous mode, a move until
    /// stopped).
    Jog(Channel, Direction),
    /// MOT_SET_HOMEPARAMS.
    SetHome(Channel, HomeParams),
    /// MOT_REQ_HOMEPARAMS.
    RequestHome(Channel),
    /// MOT_MOVE_HOME.
    Home(Channel),
    /// MOT_MOVE_RELATIVE: by this distance, or by the stored one.
    MoveRelative(Channel, Option<i32>),
    /// MOT_MOVE_ABSOLUTE: to this position, or to the stored one.
    MoveAbsolute(Channel, Option<i32>),
    /// MOT_REQ_STATUSBITS.
    RequestStatusBits(Channel),
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
    /// Hardware type (the protocol names 44, DC servo controller, and 45,
    /// multi-channel motherboard).
    pub kind: u16,
    /// Free text about the unit.
    pub notes: String,
}

/// A status update (MOT_GET_DCSTATUSUPDATE, MOVE_COMPLETED, MOVE_STOPPED).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DcStatus {
    /// The channel.
    pub channel: Channel,
    /// Position counter, encoder counts.
    pub position: i32,
    /// Signed velocity as the status word carries it (informational).
    pub velocity: i16,
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

    /// Homed since the controller powered up (bit 10): only then does the
    /// position counter refer to the actuator's travel.
    pub fn homed(&self) -> bool {
        self.bits & 0x400 != 0
    }

    /// What the bits report that no move should go on after, in words: a
    /// hardware limit switch, a motion error, the motor's current limit, a
    /// disabled channel (empty when none).
    pub fn faults(&self) -> Vec<&'static str> {
        const FAULT_BITS: [(u32, &str); 4] = [
            (0x0000_0001, "its forward hardware limit switch is active"),
            (0x0000_0002, "its reverse hardware limit switch is active"),
            (
                0x0000_4000,
                "it reports a motion error (position error too large)",
            ),
            (0x0100_0000, "its motor reached the current limit"),
        ];
        let mut faults: Vec<&str> = (FAULT_BITS.iter())
            .filter(|(bit, _)| self.bits & bit != 0)
            .map(|(_, what)| *what)
            .collect();
        if !self.enabled() {
            faults.push("its channel is disabled");
        }
        faults
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
    /// MOT_MOVE_HOMED.
    Homed(Channel),
    /// The get message of a one-value parameter.
    Param(Channel, Param, i32),
    /// MOT_GET_JOGPARAMS.
    Jog(Channel, JogParams),
    /// MOT_GET_HOMEPARAMS.
    Home(Channel, HomeParams),
    /// MOT_GET_STATUSBITS.
    StatusBits(Channel, u32),
}

impl Reply {
    /// The channel the reply is about, when it is about one.
    pub fn channel(&self) -> Option<Channel> {
        match self {
            Self::Info(_) => None,
            Self::Enabled(channel, _)
            | Self::Velocity(channel, _)
            | Self::Position(channel, _)
            | Self::Homed(channel)
            | Self::Param(channel, ..)
            | Self::Jog(channel, _)
            | Self::Home(channel, _)
            | Self::StatusBits(channel, _) => Some(*channel),
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
        let long = |id: u16, data: Vec<u8>| Frame::Long {
            id,
            dest: DEVICE,
            source: HOST,
            data,
        };
        match self {
            Self::RequestInfo => short(HW_REQ_INFO, 0, 0),
            Self::StartUpdates => short(HW_START_UPDATEMSGS, 0, 0),
            Self::StopUpdates => short(HW_STOP_UPDATEMSGS, 0, 0),
            Self::Enable(Channel(c), on) => {
                short(MOD_SET_CHANENABLESTATE, c, if on { 1 } else { 2 })
            }
            Self::RequestEnabled(Channel(c)) => short(MOD_REQ_CHANENABLESTATE, c, 0),
            Self::SetVelocity(channel, p) => long(MOT_SET_VELPARAMS, p.data(channel)),
            Self::RequestVelocity(Channel(c)) => short(MOT_REQ_VELPARAMS, c, 0),
            Self::MoveVelocity(Channel(c), direction) => {
                short(MOT_MOVE_VELOCITY, c, direction.param())
            }
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
            Self::Identify => short(MOD_IDENTIFY, 0, 0),
            Self::Disconnect => short(HW_DISCONNECT, 0, 0),
            Self::SetPosition(channel, value) => {
                long(MOT_SET_POSCOUNTER, value_data(channel, value))
            }
            Self::SetParam(channel, param, value) => {
                long(param.ids().0, value_data(channel, value))
            }
            Self::RequestParam(Channel(c), param) => short(param.ids().1, c, 0),
            Self::SetJog(channel, p) => long(MOT_SET_JOGPARAMS, p.data(channel)),
            Self::RequestJog(Channel(c)) => short(MOT_REQ_JOGPARAMS, c, 0),
            Self::Jog(Channel(c), direction) => short(MOT_MOVE_JOG, c, direction.param()),
            Self::SetHome(channel, p) => long(MOT_SET_HOMEPARAMS, p.data(channel)),
            Self::RequestHome(Channel(c)) => short(MOT_REQ_HOMEPARAMS, c, 0),
            Self::Home(Channel(c)) => short(MOT_MOVE_HOME, c, 0),
            Self::MoveRelative(Channel(c), None) => short(MOT_MOVE_RELATIVE, c, 0),
            Self::MoveRelative(channel, Some(value)) => {
                long(MOT_MOVE_RELATIVE, value_data(channel, value))
            }
            Self::MoveAbsolute(Channel(c), None) => short(MOT_MOVE_ABSOLUTE, c, 0),
            Self::MoveAbsolute(channel, Some(value)) => {
                long(MOT_MOVE_ABSOLUTE, value_data(channel, value))
            }
            Self::RequestStatusBits(Channel(c)) => short(MOT_REQ_STATUSBITS, c, 0),
        }
    }
}

/// The data packet of a one-value message: the channel, then the value.
fn value_data(Channel(c): Channel, value: i32) -> Vec<u8> {
    let mut data = u16::from(c).to_le_bytes().to_vec();
    data.extend_from_slice(&value.to_le_bytes());
    data
}

impl Direction {
    /// The parameter byte of a move: 1 forward, 2 reverse.
    fn param(self) -> u8 {
        match self {
            Self::Forward => 1,
            Self::Reverse => 2,
        }
    }
}

impl JogParams {
    fn data(&self, Channel(c): Channel) -> Vec<u8> {
        let mut data = u16::from(c).to_le_bytes().to_vec();
        data.extend_from_slice(&self.mode.to_le_bytes());
        for value in [
            self.step,
            self.min_velocity,
            self.acceleration,
            self.max_velocity,
        ] {
            data.extend_from_slice(&value.to_le_bytes());
        }
        data.extend_from_slice(&self.stop_mode.to_le_bytes());
        data
    }
}

impl HomeParams {
    fn data(&self, Channel(c): Channel) -> Vec<u8> {
        let mut data = u16::from(c).to_le_bytes().to_vec();
        data.extend_from_slice(&self.direction.to_le_bytes());
        data.extend_from_slice(&self.limit_switch.to_le_bytes());
        data.extend_from_slice(&self.velocity.to_le_bytes());
        data.extend_from_slice(&self.offset.to_le_bytes());
        data
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
        let direction = |p: u8| {
            on_off(p, "direction").map(|forward| {
                if forward {
                    Direction::Forward
                } else {
                    Direction::Reverse
                }
            })
        };
        match frame {
            Frame::Short {
                id, param1, param2, ..
            } => {
                let c = Channel(*param1);
                if let Some(param) = Param::ALL.into_iter().find(|p| p.ids().1 == *id) {
                    return Ok(Self::RequestParam(c, param));
                }
                Ok(match *id {
                    HW_REQ_INFO => Self::RequestInfo,
                    HW_START_UPDATEMSGS => Self::StartUpdates,
                    HW_STOP_UPDATEMSGS => Self::StopUpdates,
                    HW_DISCONNECT => Self::Disconnect,
                    MOD_IDENTIFY => Self::Identify,
                    MOT_ACK_DCSTATUSUPDATE => Self::AckStatus,
                    MOD_SET_CHANENABLESTATE => Self::Enable(c, on_off(*param2, "enable state")?),
                    MOD_REQ_CHANENABLESTATE => Self::RequestEnabled(c),
                    MOT_REQ_VELPARAMS => Self::RequestVelocity(c),
                    MOT_REQ_JOGPARAMS => Self::RequestJog(c),
                    MOT_REQ_HOMEPARAMS => Self::RequestHome(c),
                    MOT_REQ_STATUSBITS => Self::RequestStatusBits(c),
                    MOT_MOVE_HOME => Self::Home(c),
                    MOT_MOVE_RELATIVE => Self::MoveRelative(c, None),
                    MOT_MOVE_ABSOLUTE => Self::MoveAbsolute(c, None),
                    MOT_MOVE_VELOCITY => Self::MoveVelocity(c, direction(*param2)?),
                    MOT_MOVE_JOG => Self::Jog(c, direction(*param2)?),
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
            Frame::Long { id, data, .. } => {
                let value = || {
                    let mut f = Fields::of(*id, data, 6)?;
                    Ok::<_, AptError>((Channel(f.u16() as u8), f.i32()))
                };
                if let Some(param) = Param::ALL.into_iter().find(|p| p.ids().0 == *id) {
                    let (c, v) = value()?;
                    return Ok(Self::SetParam(c, param, v));
                }
                Ok(match *id {
                    MOT_SET_VELPARAMS => {
                        let (channel, params) = Fields::of(*id, data, 14)?.velocity_params();
                        Self::SetVelocity(channel, params)
                    }
                    MOT_SET_JOGPARAMS => {
                        let (channel, params) = Fields::of(*id, data, 22)?.jog_params();
                        Self::SetJog(channel, params)
                    }
                    MOT_SET_HOMEPARAMS => {
                        let (channel, params) = Fields::of(*id, data, 14)?.home_params();
                        Self::SetHome(channel, params)
                    }
                    MOT_SET_POSCOUNTER => {
                        let (c, v) = value()?;
                        Self::SetPosition(c, v)
                    }
                    MOT_MOVE_RELATIVE => {
                        let (c, v) = value()?;
                        Self::MoveRelative(c, Some(v))
                    }
                    MOT_MOVE_ABSOLUTE => {
                        let (c, v) = value()?;
                        Self::MoveAbsolute(c, Some(v))
                    }
                    other => {
                        return Err(AptError::Unexpected(format!(
                            "command 0x{other:04x} with {} data bytes",
                            data.len()
                        )));
                    }
                })
            }
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

    fn jog_params(&mut self) -> (Channel, JogParams) {
        let channel = Channel(self.u16() as u8);
        let params = JogParams {
            mode: self.u16(),
            step: self.i32(),
            min_velocity: self.i32(),
            acceleration: self.i32(),
            max_velocity: self.i32(),
            stop_mode: self.u16(),
        };
        (channel, params)
    }

    fn home_params(&mut self) -> (Channel, HomeParams) {
        let channel = Channel(self.u16() as u8);
        let params = HomeParams {
            direction: self.u16(),
            limit_switch: self.u16(),
            velocity: self.i32(),
            offset: self.i32(),
        };
        (channel, params)
    }

    fn status(&mut self) -> DcStatus {
        DcStatus {
            channel: Channel(self.u16() as u8),
            position: self.i32(),
            velocity: self.u16() as i16,
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
            Frame::Short {
                id: MOT_MOVE_HOMED,
                param1,
                ..
            } => Ok(Self::Homed(Channel(*param1))),
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
                let kind = f.u16();
                let [minor, interim, major, _] = f.take::<4>();
                let notes = f.text::<48>();
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
                    kind,
                    notes,
                }))
            }
            MOT_GET_JOGPARAMS => {
                let (channel, params) = Fields::of(id, data, 22)?.jog_params();
                Ok(Self::Jog(channel, params))
            }
            MOT_GET_HOMEPARAMS => {
                let (channel, params) = Fields::of(id, data, 14)?.home_params();
                Ok(Self::Home(channel, params))
            }
            MOT_GET_STATUSBITS => {
                let mut f = Fields::of(id, data, 6)?;
                Ok(Self::StatusBits(Channel(f.u16() as u8), f.u32()))
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
            _ => match Param::ALL.into_iter().find(|p| p.ids().2 == id) {
                Some(param) => {
                    let mut f = Fields::of(id, data, 6)?;
                    Ok(Self::Param(Channel(f.u16() as u8), param, f.i32()))
                }
                None => Err(AptError::Unexpected(format!(
                    "message 0x{id:04x} with {} data bytes",
                    data.len()
                ))),
            },
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
                data.extend_from_slice(&info.kind.to_le_bytes());
                let version: Vec<u8> = info
                    .firmware
                    .split('.')
                    .rev()
                    .map(|p| p.parse().unwrap_or(0))
                    .chain(std::iter::repeat(0))
                    .take(4)
                    .collect();
                data.extend_from_slice(&version);
                let mut notes = [0u8; 48];
                for (slot, byte) in notes.iter_mut().zip(info.notes.bytes()) {
                    *slot = byte;
                }
                data.extend_from_slice(&notes);
                data.extend_from_slice(&[0u8; 12]);
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
            Self::Position(channel, position) => {
                long(MOT_GET_POSCOUNTER, value_data(*channel, *position))
            }
            Self::Homed(Channel(c)) => Frame::Short {
                id: MOT_MOVE_HOMED,
                param1: *c,
                param2: 0,
                dest: HOST,
                source: DEVICE,
            },
            Self::Param(channel, param, value) => long(param.ids().2, value_data(*channel, *value)),
            Self::Jog(channel, p) => long(MOT_GET_JOGPARAMS, p.data(*channel)),
            Self::Home(channel, p) => long(MOT_GET_HOMEPARAMS, p.data(*channel)),
            Self::StatusBits(Channel(c), bits) => {
                let mut data = u16::from(*c).to_le_bytes().to_vec();
                data.extend_from_slice(&bits.to_le_bytes());
                long(MOT_GET_STATUSBITS, data)
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
    const JOG: JogParams = JogParams {
        mode: 2,
        step: 3455,
        min_velocity: 0,
        acceleration: 396,
        max_velocity: 1_159_471,
        stop_mode: 2,
    };
    const HOME: HomeParams = HomeParams {
        direction: 2,
        limit_switch: 1,
        velocity: 772_981,
        offset: 3455,
    };

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
            Command::Identify,
            Command::Disconnect,
            Command::SetPosition(CH, -5),
            Command::SetParam(CH, Param::Backlash, 276),
            Command::RequestParam(CH, Param::AbsolutePosition),
            Command::SetJog(CH, JOG),
            Command::RequestJog(CH),
            Command::Jog(CH, Direction::Reverse),
            Command::SetHome(CH, HOME),
            Command::RequestHome(CH),
            Command::Home(CH),
            Command::MoveRelative(CH, None),
            Command::MoveRelative(CH, Some(-34_555)),
            Command::MoveAbsolute(CH, Some(69_110)),
            Command::RequestStatusBits(CH),
        ] {
            assert_eq!(Command::from_frame(&command.to_frame()).unwrap(), command);
        }
    }

    #[test]
    fn replies_round_trip_through_frames() {
        let status = DcStatus {
            channel: CH,
            position: -123_456,
            velocity: -7,
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
                kind: 44,
                notes: "a note".into(),
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
            Reply::Homed(CH),
            Reply::Param(CH, Param::RelativeDistance, -7),
            Reply::Jog(CH, JOG),
            Reply::Home(CH, HOME),
            Reply::StatusBits(CH, 0x8000_0400),
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
            kind: 44,
            notes: String::new(),
        });
        assert_eq!(info.channel(), None);
    }
}
