//! A simulated KDC101 driving a Z8 actuator: it answers every message a
//! KDC101 user's software sends as the APT protocol documents it —
//! identification, channel enable, velocity, jog, homing and move
//! parameters, velocity, jog, relative, absolute and homing moves, stops,
//! position and encoder counters, status requests and periodic status
//! updates — and moves a simulated carriage with finite acceleration,
//! hardware limit switches and backlash. Its hardware can be made to fail
//! ([`Malfunction`], a counter jump, a power cycle) for tests of the
//! driver. [`crate::PtySimulator`] serves it
//! over a pseudo-terminal, so the real driver, or any other APT client,
//! runs unchanged against it.

use crate::apt::{
    AptError, Channel, Command, DcStatus, Direction, Frame, HardwareInfo, HomeParams, JogParams,
    Param, Reply, StopMode, VelocityParams, Z8Units,
};

/// Status bits of the KDC101.
const FORWARD_LIMIT: u32 = 0x01;
const REVERSE_LIMIT: u32 = 0x02;
const MOVING_FORWARD: u32 = 0x10;
const MOVING_REVERSE: u32 = 0x20;
const JOGGING_FORWARD: u32 = 0x40;
const JOGGING_REVERSE: u32 = 0x80;
const MOTOR_CONNECTED: u32 = 0x100;
const HOMING: u32 = 0x200;
const HOMED: u32 = 0x400;
const ENABLED: u32 = 0x8000_0000;
/// The interval of status updates once started (HW_START_UPDATEMSGS), s.
const UPDATE_INTERVAL_S: f64 = 0.1;
/// The hardware type reported (the protocol's DC servo controller).
const HARDWARE_TYPE: u16 = 44;

/// The simulated actuator's build.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ActuatorModel {
    /// Travel between the limit switches, mm (Z812: 12).
    pub travel_mm: f64,
    /// Lost motion on reversal, mm (the paper's stages: up to 8 µm).
    pub backlash_mm: f64,
    /// Where the motor starts, mm.
    pub start_mm: f64,
    /// Whether the stage starts homed (as after an operator homed it once
    /// since power-up), its counter reading the motor's distance from the
    /// reverse limit.
    pub homed: bool,
}

impl Default for ActuatorModel {
    fn default() -> Self {
        Self {
            travel_mm: 12.0,
            backlash_mm: 0.008,
            start_mm: 6.0,
            homed: true,
        }
    }
}

/// Ways the simulated hardware itself fails, for tests of the driver.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Malfunction {
    /// The motor runs this many times faster than its profile says.
    Runaway(f64),
    /// The encoder's counter stays where it is while the motor moves on.
    FrozenEncoder,
}

/// What the motor is doing.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Motion {
    Idle,
    /// Until stopped: a velocity move, or a continuous jog.
    Velocity {
        direction: Direction,
        jog: bool,
    },
    /// To a position counter value, mm (relative, absolute and step-jog
    /// moves, and the last leg of homing).
    To {
        target_mm: f64,
        homing: bool,
        jog: bool,
    },
    /// Toward the home limit switch.
    Homing,
    Stopping,
}

/// A KDC101 with one channel.
#[derive(Clone, Debug)]
pub struct SimulatedController {
    model: ActuatorModel,
    units: Z8Units,
    serial: u32,
    enabled: bool,
    updates: bool,
    since_update_s: f64,
    params: VelocityParams,
    jog: JogParams,
    home: HomeParams,
    backlash: i32,
    relative_distance: i32,
    absolute_position: i32,
    homed: bool,
    /// The motor position the position counter calls zero, mm.
    origin_mm: f64,
    motor_mm: f64,
    carriage_mm: f64,
    velocity_mm_s: f64,
    motion: Motion,
    /// Simulated time since power-up, s.
    elapsed_s: f64,
    malfunction: Option<Malfunction>,
    /// The counter's value while the encoder is frozen, mm.
    frozen_mm: Option<f64>,
}

impl SimulatedController {
    /// A controller with serial number `serial`, disabled, at rest, with
    /// its counter reading the motor's distance from the reverse limit.
    pub fn new(serial: u32, model: ActuatorModel) -> Self {
        let units = Z8Units::default();
        Self {
            model,
            units,
            serial,
            enabled: false,
            updates: false,
            since_update_s: 0.0,
            params: VelocityParams {
                min_velocity: 0,
                acceleration: units.acceleration(1.5),
                max_velocity: units.velocity(2.3),
            },
            jog: JogParams {
                mode: 2,
                step: units.counts(0.1),
                min_velocity: 0,
                acceleration: units.acceleration(1.5),
                max_velocity: units.velocity(2.3),
                stop_mode: 2,
            },
            home: HomeParams {
                direction: 2,
                limit_switch: 1,
                velocity: units.velocity(1.0),
                offset: 0,
            },
            backlash: 0,
            relative_distance: 0,
            absolute_position: 0,
            homed: model.homed,
            origin_mm: 0.0,
            motor_mm: model.start_mm,
            carriage_mm: model.start_mm,
            velocity_mm_s: 0.0,
            motion: Motion::Idle,
            elapsed_s: 0.0,
            malfunction: None,
            frozen_mm: None,
        }
    }

    /// Where the carriage (and so the sample) is, mm: the motor's position
    /// less the backlash not yet taken up.
    pub fn carriage_mm(&self) -> f64 {
        self.carriage_mm
    }

    /// The motor's signed speed, mm/s.
    pub fn speed_mm_s(&self) -> f64 {
        self.velocity_mm_s
    }

    /// Simulated time since power-up, s: the sum of every `advance`.
    pub fn elapsed_s(&self) -> f64 {
        self.elapsed_s
    }

    /// Makes the hardware fail from now on (or work again).
    pub fn set_malfunction(&mut self, malfunction: Option<Malfunction>) {
        self.frozen_mm = (malfunction == Some(Malfunction::FrozenEncoder))
            .then_some(self.motor_mm - self.origin_mm);
        self.malfunction = malfunction;
    }

    /// Shifts the position counter by `mm` at once, as a glitching
    /// encoder does.
    pub fn jump_counter(&mut self, mm: f64) {
        self.origin_mm -= mm;
    }

    /// A power cycle: the motor stops where it is, the counter reads 0
    /// there, the stage is no longer homed, every parameter is back at its
    /// power-up value, and the channel is enabled (as a KDC101 powers up).
    pub fn power_cycle(&mut self) {
        let (motor_mm, carriage_mm, elapsed_s) = (self.motor_mm, self.carriage_mm, self.elapsed_s);
        *self = Self {
            motor_mm,
            carriage_mm,
            origin_mm: motor_mm,
            enabled: true,
            homed: false,
            elapsed_s,
            ..Self::new(self.serial, self.model)
        };
    }

    /// Whether status updates are switched on (HW_START_UPDATEMSGS).
    pub fn sends_updates(&self) -> bool {
        self.updates
    }

    /// Whether the stage has been homed since power-up.
    pub fn homed(&self) -> bool {
        self.homed
    }

    /// Answers one frame from the host: the replies to send back.
    pub fn handle(&mut self, frame: &Frame) -> Result<Vec<Frame>, AptError> {
        let command = Command::from_frame(frame)?;
        let reply = |r: Reply| vec![r.to_frame()];
        Ok(match command {
            Command::RequestInfo => reply(Reply::Info(HardwareInfo {
                serial: self.serial,
                model: "KDC101".into(),
                firmware: "3.0.10".into(),
                hardware_version: 1,
                channels: 1,
                kind: HARDWARE_TYPE,
                notes: "Brushed DC Servo Controller (simulated)".into(),
            })),
            Command::StartUpdates => {
                self.updates = true;
                self.since_update_s = 0.0;
                Vec::new()
            }
            Command::StopUpdates | Command::Disconnect => {
                self.updates = false;
                Vec::new()
            }
            Command::AckStatus | Command::Identify => Vec::new(),
            Command::Enable(_, on) => {
                self.enabled = on;
                if !on {
                    self.halt();
                }
                Vec::new()
            }
            Command::RequestEnabled(channel) => reply(Reply::Enabled(channel, self.enabled)),
            Command::SetVelocity(_, params) => {
                self.params = params;
                Vec::new()
            }
            Command::RequestVelocity(channel) => reply(Reply::Velocity(channel, self.params)),
            Command::SetJog(_, jog) => {
                self.jog = jog;
                Vec::new()
            }
            Command::RequestJog(channel) => reply(Reply::Jog(channel, self.jog)),
            Command::SetHome(_, home) => {
                self.home = home;
                Vec::new()
            }
            Command::RequestHome(channel) => reply(Reply::Home(channel, self.home)),
            Command::SetParam(_, param, value) => {
                match param {
                    Param::Backlash => self.backlash = value,
                    Param::RelativeDistance => self.relative_distance = value,
                    Param::AbsolutePosition => self.absolute_position = value,
                    // The encoder and the position counter are one on a
                    // DC servo.
                    Param::EncoderCount => self.set_counter(value),
                }
                Vec::new()
            }
            Command::RequestParam(channel, param) => {
                let value = match param {
                    Param::Backlash => self.backlash,
                    Param::RelativeDistance => self.relative_distance,
                    Param::AbsolutePosition => self.absolute_position,
                    Param::EncoderCount => self.counter(),
                };
                reply(Reply::Param(channel, param, value))
            }
            Command::SetPosition(_, value) => {
                self.set_counter(value);
                Vec::new()
            }
            Command::MoveVelocity(_, direction) => {
                self.start(Motion::Velocity {
                    direction,
                    jog: false,
                });
                Vec::new()
            }
            Command::Jog(_, direction) => {
                let motion = if self.jog.mode == 1 {
                    Motion::Velocity {
                        direction,
                        jog: true,
                    }
                } else {
                    let step = self.units.mm(self.jog.step.abs());
                    let step = match direction {
                        Direction::Forward => step,
                        Direction::Reverse => -step,
                    };
                    Motion::To {
                        target_mm: self.counter_mm() + step,
                        homing: false,
                        jog: true,
                    }
                };
                self.start(motion);
                Vec::new()
            }
            Command::MoveRelative(_, distance) => {
                let distance = distance.unwrap_or(self.relative_distance);
                self.start(Motion::To {
                    target_mm: self.counter_mm() + self.units.mm(distance),
                    homing: false,
                    jog: false,
                });
                Vec::new()
            }
            Command::MoveAbsolute(_, position) => {
                let position = position.unwrap_or(self.absolute_position);
                self.start(Motion::To {
                    target_mm: self.units.mm(position),
                    homing: false,
                    jog: false,
                });
                Vec::new()
            }
            Command::Home(_) => {
                self.homed = false;
                self.start(Motion::Homing);
                Vec::new()
            }
            Command::Stop(_, StopMode::Immediate) => {
                self.halt();
                reply(Reply::MoveStopped(self.status()))
            }
            Command::Stop(_, StopMode::Profiled) => {
                if self.motion == Motion::Idle {
                    reply(Reply::MoveStopped(self.status()))
                } else {
                    self.motion = Motion::Stopping;
                    Vec::new()
                }
            }
            Command::RequestPosition(channel) => reply(Reply::Position(channel, self.counter())),
            Command::RequestStatus(_) => reply(Reply::Status(self.status())),
            Command::RequestStatusBits(channel) => {
                reply(Reply::StatusBits(channel, self.status().bits))
            }
        })
    }

    /// Starts `motion` if the channel is enabled (a disabled one ignores
    /// moves).
    fn start(&mut self, motion: Motion) {
        if self.enabled {
            self.motion = motion;
        }
    }

    /// The position counter, mm.
    fn counter_mm(&self) -> f64 {
        self.frozen_mm.unwrap_or(self.motor_mm - self.origin_mm)
    }

    fn counter(&self) -> i32 {
        self.units.counts(self.counter_mm())
    }

    fn set_counter(&mut self, value: i32) {
        self.origin_mm = self.motor_mm - self.units.mm(value);
    }

    /// Moves the simulation on by `dt` seconds; returns what the controller
    /// sends by itself: MOVE_STOPPED when a stop completes or a limit
    /// switch trips, MOVE_COMPLETED when a move arrives, MOVE_HOMED, and
    /// status updates every 100 ms while they are on.
    pub fn advance(&mut self, dt: f64) -> Vec<Frame> {
        self.elapsed_s += dt;
        let mut events = Vec::new();
        let (top, accel) = self.profile();
        let step = accel * dt;
        let wanted = match self.motion {
            Motion::Velocity { direction, .. } => match direction {
                Direction::Forward => top,
                Direction::Reverse => -top,
            },
            Motion::Homing => match self.home.direction {
                1 => top,
                _ => -top,
            },
            Motion::To { target_mm, .. } => {
                let remaining = target_mm - self.counter_mm();
                // The fastest speed from which the target can still be
                // reached by braking.
                let brake = (2.0 * accel * remaining.abs()).sqrt();
                remaining.signum() * top.min(brake)
            }
            Motion::Stopping | Motion::Idle => 0.0,
        };
        let wanted = match self.malfunction {
            Some(Malfunction::Runaway(factor)) => wanted * factor,
            _ => wanted,
        };
        self.velocity_mm_s += (wanted - self.velocity_mm_s).clamp(-step, step);
        let before = self.counter_mm();
        self.motor_mm += self.velocity_mm_s * dt;
        if let Motion::To {
            target_mm, homing, ..
        } = self.motion
        {
            let (a, b) = (before - target_mm, self.counter_mm() - target_mm);
            if a == 0.0 || b == 0.0 || a.signum() != b.signum() || b.abs() < 1e-7 {
                self.motor_mm = target_mm + self.origin_mm;
                self.halt();
                if homing {
                    self.origin_mm = self.motor_mm;
                    self.homed = true;
                    events.push(Reply::Homed(Channel(1)).to_frame());
                } else {
                    events.push(Reply::MoveCompleted(self.status()).to_frame());
                }
            }
        }
        if self.motor_mm <= 0.0 || self.motor_mm >= self.model.travel_mm {
            self.motor_mm = self.motor_mm.clamp(0.0, self.model.travel_mm);
            match self.motion {
                // The home switch: back off by the offset, then zero there.
                Motion::Homing => {
                    self.velocity_mm_s = 0.0;
                    let offset = self.units.mm(self.home.offset.abs());
                    let away = if self.motor_mm <= 0.0 {
                        offset
                    } else {
                        -offset
                    };
                    self.motion = Motion::To {
                        target_mm: self.counter_mm() + away,
                        homing: true,
                        jog: false,
                    };
                }
                Motion::Idle | Motion::To { homing: true, .. } => {}
                _ => {
                    self.halt();
                    events.push(Reply::MoveStopped(self.status()).to_frame());
                }
            }
        }
        let play = self.model.backlash_mm;
        self.carriage_mm = self.carriage_mm.clamp(self.motor_mm - play, self.motor_mm);
        if self.motion == Motion::Stopping && self.velocity_mm_s == 0.0 {
            self.motion = Motion::Idle;
            events.push(Reply::MoveStopped(self.status()).to_frame());
        }
        if self.updates {
            self.since_update_s += dt;
            if self.since_update_s >= UPDATE_INTERVAL_S {
                self.since_update_s %= UPDATE_INTERVAL_S;
                events.push(Reply::Status(self.status()).to_frame());
            }
        }
        events
    }

    /// The top speed (mm/s) and acceleration (mm/s²) of the present motion.
    fn profile(&self) -> (f64, f64) {
        let per_accel = f64::from(self.units.acceleration(1.0).max(1));
        let (velocity, acceleration) = match self.motion {
            Motion::Velocity { jog: true, .. } | Motion::To { jog: true, .. } => {
                (self.jog.max_velocity, self.jog.acceleration)
            }
            Motion::Homing | Motion::To { homing: true, .. } => {
                (self.home.velocity, self.params.acceleration)
            }
            _ => (self.params.max_velocity, self.params.acceleration),
        };
        (
            self.units.mm_per_s(velocity).abs(),
            f64::from(acceleration.max(1)) / per_accel,
        )
    }

    fn halt(&mut self) {
        self.velocity_mm_s = 0.0;
        self.motion = Motion::Idle;
    }

    /// The status the controller reports now.
    pub fn status(&self) -> DcStatus {
        let mut bits = MOTOR_CONNECTED;
        if self.enabled {
            bits |= ENABLED;
        }
        if self.homed {
            bits |= HOMED;
        }
        if self.motor_mm >= self.model.travel_mm {
            bits |= FORWARD_LIMIT;
        }
        if self.motor_mm <= 0.0 {
            bits |= REVERSE_LIMIT;
        }
        let jogging = matches!(
            self.motion,
            Motion::Velocity { jog: true, .. } | Motion::To { jog: true, .. }
        );
        if matches!(
            self.motion,
            Motion::Homing | Motion::To { homing: true, .. }
        ) {
            bits |= HOMING;
        }
        if self.velocity_mm_s > 0.0 {
            bits |= if jogging {
                JOGGING_FORWARD
            } else {
                MOVING_FORWARD
            };
        } else if self.velocity_mm_s < 0.0 {
            bits |= if jogging {
                JOGGING_REVERSE
            } else {
                MOVING_REVERSE
            };
        }
        DcStatus {
            channel: Channel(1),
            position: self.counter(),
            // The status word's signed velocity: encoder counts per second
            // / 1,000 (informational; the driver does not read it).
            velocity: (self.velocity_mm_s * self.units.counts_per_mm / 1000.0)
                .round()
                .clamp(f64::from(i16::MIN), f64::from(i16::MAX)) as i16,
            bits,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CH: Channel = Channel(1);

    fn send(c: &mut SimulatedController, command: Command) -> Vec<Reply> {
        c.handle(&command.to_frame())
            .unwrap()
            .iter()
            .map(|f| Reply::from_frame(f).unwrap())
            .collect()
    }

    fn run(c: &mut SimulatedController, seconds: f64) -> Vec<Reply> {
        let mut events = Vec::new();
        for _ in 0..(seconds * 1000.0).round() as usize {
            events.extend(
                c.advance(0.001)
                    .iter()
                    .map(|f| Reply::from_frame(f).unwrap()),
            );
        }
        events
    }

    #[test]
    fn identifies_and_moves_only_when_enabled() {
        let mut c = SimulatedController::new(27_000_042, ActuatorModel::default());
        let info = send(&mut c, Command::RequestInfo);
        assert!(
            matches!(&info[..], [Reply::Info(i)] if i.serial == 27_000_042 && i.model == "KDC101")
        );
        send(&mut c, Command::MoveVelocity(CH, Direction::Forward));
        run(&mut c, 0.5);
        assert_eq!(c.carriage_mm(), 6.0, "a disabled channel does not move");
        send(&mut c, Command::Enable(CH, true));
        assert_eq!(
            send(&mut c, Command::RequestEnabled(CH)),
            [Reply::Enabled(CH, true)]
        );
    }

    #[test]
    fn accelerates_to_the_set_velocity_and_stops_with_a_profile() {
        let mut c = SimulatedController::new(1, ActuatorModel::default());
        let units = Z8Units::default();
        send(&mut c, Command::Enable(CH, true));
        let params = VelocityParams {
            min_velocity: 0,
            acceleration: units.acceleration(2.0),
            max_velocity: units.velocity(1.0),
        };
        send(&mut c, Command::SetVelocity(CH, params));
        assert_eq!(
            send(&mut c, Command::RequestVelocity(CH)),
            [Reply::Velocity(CH, params)]
        );
        send(&mut c, Command::MoveVelocity(CH, Direction::Forward));
        assert!(run(&mut c, 1.0).is_empty());
        // 0.5 s accelerating (0.25 mm), then 0.5 s at 1 mm/s.
        let [Reply::Position(_, counts)] = send(&mut c, Command::RequestPosition(CH))[..] else {
            panic!("no position")
        };
        assert!(
            (units.mm(counts) - 6.75).abs() < 0.01,
            "{}",
            units.mm(counts)
        );
        assert!(c.status().moving());
        assert!(send(&mut c, Command::Stop(CH, StopMode::Profiled)).is_empty());
        let events = run(&mut c, 1.0);
        assert!(
            matches!(&events[..], [Reply::MoveStopped(s)] if !s.moving()),
            "{events:?}"
        );
    }

    #[test]
    fn limit_switches_stop_the_motor_and_reversal_takes_up_backlash() {
        let mut c = SimulatedController::new(
            1,
            ActuatorModel {
                travel_mm: 6.5,
                ..Default::default()
            },
        );
        send(&mut c, Command::Enable(CH, true));
        send(&mut c, Command::MoveVelocity(CH, Direction::Forward));
        let events = run(&mut c, 3.0);
        assert!(
            matches!(&events[..], [Reply::MoveStopped(s)] if s.at_limit()),
            "{events:?}"
        );
        assert!(
            (c.carriage_mm() - (6.5 - 0.008)).abs() < 1e-9,
            "{}",
            c.carriage_mm()
        );
        send(&mut c, Command::MoveVelocity(CH, Direction::Reverse));
        run(&mut c, 0.2);
        let moved = 6.5 - c.status().position as f64 / Z8Units::default().counts_per_mm;
        assert!(moved > 0.008, "the motor moved {moved} mm");
        assert!(
            (6.5 - 0.008 - c.carriage_mm() - (moved - 0.008)).abs() < 1e-4,
            "the carriage lags by the backlash"
        );
        send(&mut c, Command::Stop(CH, StopMode::Immediate));
        assert!(!c.status().moving());
    }
}
