//! A simulated KDC101 driving a Z8 actuator: it answers the commands the
//! driver sends as the real controller does and moves a simulated
//! carriage with finite acceleration, hardware limit switches and backlash.
//! [`crate::PtySimulator`] serves it over a pseudo-terminal, so the real
//! driver runs unchanged against it.

use crate::apt::{
    AptError, Channel, Command, DcStatus, Direction, Frame, HardwareInfo, Reply, StopMode,
    VelocityParams, Z8Units,
};

/// Status bits of the KDC101.
const FORWARD_LIMIT: u32 = 0x01;
const REVERSE_LIMIT: u32 = 0x02;
const MOVING_FORWARD: u32 = 0x10;
const MOVING_REVERSE: u32 = 0x20;
const ENABLED: u32 = 0x8000_0000;

/// The simulated actuator's build.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ActuatorModel {
    /// Travel between the limit switches, mm (Z812: 12).
    pub travel_mm: f64,
    /// Lost motion on reversal, mm (the paper's stages: up to 8 µm).
    pub backlash_mm: f64,
    /// Where the motor starts, mm.
    pub start_mm: f64,
}

impl Default for ActuatorModel {
    fn default() -> Self {
        Self {
            travel_mm: 12.0,
            backlash_mm: 0.008,
            start_mm: 6.0,
        }
    }
}

/// What the motor is doing.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Motion {
    Idle,
    Velocity(Direction),
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
    params: VelocityParams,
    motor_mm: f64,
    carriage_mm: f64,
    velocity_mm_s: f64,
    motion: Motion,
}

impl SimulatedController {
    /// A controller with serial number `serial`, disabled, at rest.
    pub fn new(serial: u32, model: ActuatorModel) -> Self {
        let units = Z8Units::default();
        Self {
            model,
            units,
            serial,
            enabled: false,
            updates: false,
            params: VelocityParams {
                min_velocity: 0,
                acceleration: units.acceleration(1.5),
                max_velocity: units.velocity(2.3),
            },
            motor_mm: model.start_mm,
            carriage_mm: model.start_mm,
            velocity_mm_s: 0.0,
            motion: Motion::Idle,
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

    /// Whether status updates are switched on (HW_START_UPDATEMSGS).
    pub fn sends_updates(&self) -> bool {
        self.updates
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
            })),
            Command::StartUpdates => {
                self.updates = true;
                Vec::new()
            }
            Command::StopUpdates => {
                self.updates = false;
                Vec::new()
            }
            Command::AckStatus => Vec::new(),
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
            Command::MoveVelocity(_, direction) => {
                if self.enabled {
                    self.motion = Motion::Velocity(direction);
                }
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
            Command::RequestPosition(channel) => {
                reply(Reply::Position(channel, self.units.counts(self.motor_mm)))
            }
            Command::RequestStatus(_) => reply(Reply::Status(self.status())),
        })
    }

    /// Moves the simulation on by `dt` seconds; returns what the controller
    /// sends by itself (MOVE_STOPPED when a stop completes or a limit switch
    /// trips).
    pub fn advance(&mut self, dt: f64) -> Vec<Frame> {
        let accel = f64::from(self.params.acceleration.max(1))
            / f64::from(self.units.acceleration(1.0).max(1));
        let top = self.units.mm_per_s(self.params.max_velocity).abs();
        let wanted = match self.motion {
            Motion::Velocity(Direction::Forward) => top,
            Motion::Velocity(Direction::Reverse) => -top,
            Motion::Stopping | Motion::Idle => 0.0,
        };
        let step = accel * dt;
        self.velocity_mm_s += (wanted - self.velocity_mm_s).clamp(-step, step);
        self.motor_mm += self.velocity_mm_s * dt;
        let mut events = Vec::new();
        if self.motor_mm <= 0.0 || self.motor_mm >= self.model.travel_mm {
            self.motor_mm = self.motor_mm.clamp(0.0, self.model.travel_mm);
            if self.motion != Motion::Idle {
                self.halt();
                events.push(Reply::MoveStopped(self.status()).to_frame());
            }
        }
        let play = self.model.backlash_mm;
        self.carriage_mm = self.carriage_mm.clamp(self.motor_mm - play, self.motor_mm);
        if self.motion == Motion::Stopping && self.velocity_mm_s == 0.0 {
            self.motion = Motion::Idle;
            events.push(Reply::MoveStopped(self.status()).to_frame());
        }
        events
    }

    fn halt(&mut self) {
        self.velocity_mm_s = 0.0;
        self.motion = Motion::Idle;
    }

    /// The status the controller reports now.
    pub fn status(&self) -> DcStatus {
        let mut bits = 0;
        if self.enabled {
            bits |= ENABLED;
        }
        if self.motor_mm >= self.model.travel_mm {
            bits |= FORWARD_LIMIT;
        }
        if self.motor_mm <= 0.0 {
            bits |= REVERSE_LIMIT;
        }
        if self.velocity_mm_s > 0.0 {
            bits |= MOVING_FORWARD;
        } else if self.velocity_mm_s < 0.0 {
            bits |= MOVING_REVERSE;
        }
        DcStatus {
            channel: Channel(1),
            position: self.units.counts(self.motor_mm),
            // The status word's velocity: encoder counts per second / 1,000
            // (informational; the driver does not read it).
            velocity: (self.velocity_mm_s.abs() * self.units.counts_per_mm / 1000.0)
                .round()
                .min(f64::from(u16::MAX)) as u16,
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
