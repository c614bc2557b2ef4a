//! One KDC101-driven stage axis: the driver above the APT protocol. Travel
//! and speed limits are enforced here, below every caller: a velocity is
//! clamped to the limit, and motion toward a soft travel limit is refused
//! (the stage is stopped instead) when the stage could reach it before the
//! next command plus its braking distance.
//!
//! APT replies carry no request ids, so the driver matches them by order,
//! and after any error (a timeout, half a frame, a garbled or unexpected
//! reply) it assumes nothing about what is still in flight: before its next
//! read it gets back in step by purging the port (reading until it has
//! been quiet for 50 ms, as the protocol asks at open) and asking the
//! controller to identify itself; everything before that identification is
//! stale and discarded. A position outside any Z8 actuator's travel is
//! taken as garbled, never fed to the soft-limit check.

use crate::apt::{
    AptError, Channel, Command, Direction, FrameReader, HardwareInfo, Reply, StopMode,
    VelocityParams, Z8Units,
};
use std::io::{ErrorKind, Read, Write};
use std::ops::RangeInclusive;
use std::time::{Duration, Instant};

/// The KDC101's one channel.
pub(crate) const CHANNEL: Channel = Channel(1);
/// How long the port must stay quiet for a purge to end.
const QUIET: Duration = Duration::from_millis(50);
/// Purges and identifications tried before the driver gives up on getting
/// back in step.
const RESYNC_ATTEMPTS: usize = 3;
/// Positions a Z8-series actuator can report, mm (the Z825 travels 25 mm).
const PLAUSIBLE_MM: RangeInclusive<f64> = -1.0..=26.0;

/// What the stage may do.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AxisLimits {
    /// Soft travel limits, mm (inside the actuator's travel).
    pub min_mm: f64,
    /// Upper soft travel limit, mm.
    pub max_mm: f64,
    /// Fastest speed ever commanded, mm/s.
    pub max_speed_mm_s: f64,
    /// Acceleration of every move, mm/s².
    pub acceleration_mm_s2: f64,
    /// The longest time between two commands (the control period plus its
    /// deadline margin), s: motion is allowed only while the stage cannot
    /// pass a soft limit within it.
    pub command_interval_s: f64,
}

/// A stage axis on a serial port (or anything that reads and writes APT
/// bytes with a read timeout).
#[derive(Debug)]
pub struct Axis<P: Read + Write> {
    io: FrameReader<P>,
    units: Z8Units,
    limits: AxisLimits,
    timeout: Duration,
    speed_set: Option<i32>,
    /// The fastest the stage may still be moving, mm/s: the last speed
    /// commanded (a stop takes time, so it stays until the next move).
    last_speed: f64,
    /// Lost motion on reversal, mm.
    backlash_mm: f64,
    /// Where the carriage is estimated to be, mm: it stays put while the
    /// motor crosses the play, so it always lies in [motor - backlash,
    /// motor] (unknown until the first position read).
    carriage: Option<f64>,
    /// Whether every request sent has had its reply: false after an error
    /// until the driver is back in step.
    in_step: bool,
    /// The controller's serial number, once identified.
    serial: Option<u32>,
}

/// What a velocity command did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Commanded {
    /// Moving at this signed speed, mm/s (clamped to the limit).
    Moving(f64),
    /// Stopped: asked for zero, or motion toward a soft limit refused.
    Stopped,
}

impl<P: Read + Write> Axis<P> {
    /// Purges the port, identifies the controller and enables its channel.
    /// `timeout` bounds the wait for each reply.
    pub fn connect(
        port: P,
        units: Z8Units,
        limits: AxisLimits,
        timeout: Duration,
    ) -> Result<(Self, HardwareInfo), AptError> {
        let mut stage = Self {
            io: FrameReader::new(port),
            units,
            limits,
            timeout,
            speed_set: None,
            last_speed: 0.0,
            backlash_mm: 0.0,
            carriage: None,
            in_step: false,
            serial: None,
        };
        let info = stage.resync()?;
        // Z8 units and the one channel are the KDC101's: another model
        // would be driven wrongly.
        if !info.model.starts_with("KDC101") {
            return Err(AptError::Model { model: info.model });
        }
        stage.serial = Some(info.serial);
        stage.send(Command::Enable(CHANNEL, true))?;
        stage.send(Command::RequestEnabled(CHANNEL))?;
        match stage.await_reply(|r| matches!(r, Reply::Enabled(..)))? {
            Reply::Enabled(_, true) => {}
            other => {
                return Err(AptError::Unexpected(format!(
                    "channel not enabled: {other:?}"
                )));
            }
        }
        Ok((stage, info))
    }

    /// Mitigates `backlash_mm` of lost motion: while the motor has play to
    /// cross before the carriage follows (at the first move and after each
    /// reversal), the move is faster by that play over one command interval
    /// (within the speed limit), so it is taken up within that interval.
    pub fn with_backlash(mut self, backlash_mm: f64) -> Self {
        self.backlash_mm = if backlash_mm.is_finite() {
            backlash_mm.max(0.0)
        } else {
            0.0
        };
        self
    }

    /// Where the carriage is, mm: the motor drags it along only once it has
    /// crossed the play, so the estimate follows the motor within
    /// [motor - backlash, motor].
    pub fn carriage_mm(&mut self) -> Result<f64, AptError> {
        let motor = self.position_mm()?;
        Ok(self.follow(motor))
    }

    /// Updates the carriage estimate for the motor at `motor` mm.
    fn follow(&mut self, motor: f64) -> f64 {
        let carriage = self
            .carriage
            .unwrap_or(motor)
            .clamp(motor - self.backlash_mm, motor);
        self.carriage = Some(carriage);
        carriage
    }

    /// The position counter (the motor's position), mm.
    pub fn position_mm(&mut self) -> Result<f64, AptError> {
        if !self.in_step {
            self.resync()?;
        }
        self.send(Command::RequestPosition(CHANNEL))?;
        let Reply::Position(_, counts) = self.await_reply(|r| matches!(r, Reply::Position(..)))?
        else {
            unreachable!("await_reply returns what was asked for")
        };
        let mm = self.units.mm(counts);
        if !PLAUSIBLE_MM.contains(&mm) {
            self.lost_step();
            return Err(AptError::Unexpected(format!(
                "a position of {mm:.3} mm, outside any Z8 actuator's travel: a garbled reply"
            )));
        }
        Ok(mm)
    }

    /// Moves at `mm_per_s` (sign = direction) until the next command,
    /// within the limits: the speed is clamped, and motion toward a soft
    /// limit the stage could pass before the next command is refused with
    /// a profiled stop. A non-finite speed stops the stage.
    pub fn set_velocity(&mut self, mm_per_s: f64) -> Result<Commanded, AptError> {
        let speed = if mm_per_s.is_finite() {
            mm_per_s.clamp(-self.limits.max_speed_mm_s, self.limits.max_speed_mm_s)
        } else {
            0.0
        };
        if speed == 0.0 {
            self.stop(StopMode::Profiled)?;
            return Ok(Commanded::Stopped);
        }
        let direction = if speed > 0.0 {
            Direction::Forward
        } else {
            Direction::Reverse
        };
        let position = self.position_mm()?;
        let carriage = self.follow(position);
        // The play the motor must cross before the carriage moves this way.
        let play = match direction {
            Direction::Forward => carriage + self.backlash_mm - position,
            Direction::Reverse => position - carriage,
        };
        let speed = if play > 1e-9 {
            let boost = play / self.limits.command_interval_s.max(1e-3);
            speed.signum() * (speed.abs() + boost).min(self.limits.max_speed_mm_s)
        } else {
            speed
        };
        // The stage may still be at the last speed: bound the travel by it.
        let fastest = speed.abs().max(self.last_speed);
        let reach = fastest * self.limits.command_interval_s
            + fastest * fastest / (2.0 * self.limits.acceleration_mm_s2);
        let blocked = if speed > 0.0 {
            position + reach >= self.limits.max_mm
        } else {
            position - reach <= self.limits.min_mm
        };
        if blocked {
            self.stop(StopMode::Profiled)?;
            return Ok(Commanded::Stopped);
        }
        let units = self.units.velocity(speed.abs());
        if self.speed_set != Some(units) {
            let params = VelocityParams {
                min_velocity: 0,
                acceleration: self.units.acceleration(self.limits.acceleration_mm_s2),
                max_velocity: units,
            };
            self.send(Command::SetVelocity(CHANNEL, params))?;
            self.speed_set = Some(units);
        }
        self.send(Command::MoveVelocity(CHANNEL, direction))?;
        self.last_speed = speed.abs();
        Ok(Commanded::Moving(speed))
    }

    /// Stops the motor.
    pub fn stop(&mut self, mode: StopMode) -> Result<(), AptError> {
        self.send(Command::Stop(CHANNEL, mode))
    }

    fn send(&mut self, command: Command) -> Result<(), AptError> {
        let port = self.io.get_mut();
        port.write_all(&command.to_frame().encode())?;
        port.flush()?;
        Ok(())
    }

    /// The next reply `wanted` accepts, skipping status messages the
    /// controller sends by itself. A timeout, a malformed reply or any
    /// other message is an error: the motor is stopped (immediately) and
    /// the driver out of step before it is returned.
    fn await_reply(&mut self, wanted: impl Fn(&Reply) -> bool) -> Result<Reply, AptError> {
        let reply = self.read_reply(wanted, Stray::Refuse);
        if reply.is_err() {
            self.lost_step();
        }
        reply
    }

    /// After an error: stop the motor, drop any partial frame, and get back
    /// in step before the next read.
    fn lost_step(&mut self) {
        self.in_step = false;
        self.io.discard();
        let _ = self.send(Command::Stop(CHANNEL, StopMode::Immediate));
    }

    /// Gets back in step with the controller: purges the port, asks it to
    /// identify itself and discards everything before its answer (the
    /// controller answers in order, so that is all stale). The answer must
    /// come from the controller identified at connect.
    fn resync(&mut self) -> Result<HardwareInfo, AptError> {
        let mut failure = None;
        for _ in 0..RESYNC_ATTEMPTS {
            self.purge()?;
            self.send(Command::RequestInfo)?;
            match self.read_reply(|r| matches!(r, Reply::Info(_)), Stray::Discard) {
                Ok(Reply::Info(info)) => {
                    if let Some(serial) = self.serial.filter(|&s| s != info.serial) {
                        return Err(AptError::Unexpected(format!(
                            "controller {} answered on the port of controller {serial}",
                            info.serial
                        )));
                    }
                    self.in_step = true;
                    return Ok(info);
                }
                Ok(_) => unreachable!("read_reply returns what was asked for"),
                Err(e @ (AptError::Io(_) | AptError::Device { .. })) => return Err(e),
                Err(e) => failure = Some(e),
            }
        }
        Err(failure.unwrap_or(AptError::Timeout(self.timeout)))
    }

    /// Reads and discards whatever the port holds until it has been quiet
    /// for [`QUIET`], within the reply timeout (at least twice that).
    fn purge(&mut self) -> Result<(), AptError> {
        self.io.discard();
        let started = Instant::now();
        let mut last_byte = started;
        let mut chunk = [0u8; 256];
        loop {
            match self.io.get_mut().read(&mut chunk) {
                Ok(0) => {
                    return Err(AptError::Io(std::io::Error::new(
                        ErrorKind::UnexpectedEof,
                        "the port closed",
                    )));
                }
                Ok(_) => last_byte = Instant::now(),
                Err(e)
                    if matches!(
                        e.kind(),
                        ErrorKind::TimedOut | ErrorKind::WouldBlock | ErrorKind::Interrupted
                    ) =>
                {
                    std::thread::sleep(Duration::from_millis(1));
                }
                Err(e) => return Err(e.into()),
            }
            if last_byte.elapsed() >= QUIET {
                return Ok(());
            }
            if started.elapsed() >= self.timeout.max(2 * QUIET) {
                return Err(AptError::Unexpected(format!(
                    "the controller kept sending for {:?}: the port never went quiet",
                    started.elapsed()
                )));
            }
        }
    }

    /// The next reply `wanted` accepts within the timeout. Status messages
    /// the controller sends by itself are skipped; what else comes unasked
    /// (a reply for another channel, another message, garbled bytes) is an
    /// error or discarded, as `stray` says. A controller's error report and
    /// a failed port are errors either way.
    fn read_reply(
        &mut self,
        wanted: impl Fn(&Reply) -> bool,
        stray: Stray,
    ) -> Result<Reply, AptError> {
        let refuse = stray == Stray::Refuse;
        let deadline = Instant::now() + self.timeout;
        loop {
            match self
                .io
                .read_frame()
                .and_then(|frame| Reply::from_frame(&frame))
            {
                Ok(reply) => {
                    if let Some(channel) = reply.channel().filter(|&c| c != CHANNEL && refuse) {
                        return Err(AptError::Unexpected(format!(
                            "{reply:?}: a reply for channel {}, the KDC101 has only channel {}",
                            channel.0, CHANNEL.0
                        )));
                    }
                    if wanted(&reply) {
                        return Ok(reply);
                    }
                    let unasked = matches!(
                        reply,
                        Reply::Status(_) | Reply::MoveStopped(_) | Reply::MoveCompleted(_)
                    );
                    if refuse && !unasked {
                        return Err(AptError::Unexpected(format!("{reply:?} while waiting")));
                    }
                }
                Err(AptError::Io(e))
                    if matches!(e.kind(), ErrorKind::TimedOut | ErrorKind::WouldBlock) => {}
                Err(e @ (AptError::Io(_) | AptError::Device { .. })) => return Err(e),
                Err(e) if refuse => return Err(e),
                Err(_) => {}
            }
            if Instant::now() >= deadline {
                return Err(AptError::Timeout(self.timeout));
            }
        }
    }
}

/// What [`Axis::read_reply`] does with a message it did not ask for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Stray {
    /// An error: in step, only status messages come unasked.
    Refuse,
    /// Discarded, garbled bytes too: getting back in step.
    Discard,
}

impl<P: Read + Write> Drop for Axis<P> {
    /// Whatever ends the driver's life, the motor stops.
    fn drop(&mut self) {
        let _ = self.send(Command::Stop(CHANNEL, StopMode::Immediate));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::apt::FrameReader;
    use crate::simulator::{ActuatorModel, SimulatedController};
    use proptest::prelude::*;
    use std::cell::RefCell;
    use std::collections::VecDeque;
    use std::rc::Rc;

    /// The simulated controller behind an in-memory port: written frames
    /// are handled at once, replies are read back; an empty inbox times out.
    #[derive(Debug)]
    struct SimPort {
        controller: Rc<RefCell<SimulatedController>>,
        written: Vec<u8>,
        inbox: VecDeque<u8>,
        silent: bool,
    }

    impl Write for SimPort {
        fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
            self.written.extend_from_slice(bytes);
            let mut reader = FrameReader::new(self.written.as_slice());
            let mut used = 0;
            while let Ok(frame) = reader.read_frame() {
                used = self.written.len() - reader.get_mut().len();
                if self.silent {
                    continue;
                }
                let replies = self
                    .controller
                    .borrow_mut()
                    .handle(&frame)
                    .expect("valid commands");
                for reply in replies {
                    self.inbox.extend(reply.encode());
                }
            }
            self.written.drain(..used);
            Ok(bytes.len())
        }

        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    impl Read for SimPort {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            if self.inbox.is_empty() {
                return Err(ErrorKind::TimedOut.into());
            }
            let n = buf.len().min(self.inbox.len());
            for (slot, byte) in buf.iter_mut().zip(self.inbox.drain(..n)) {
                *slot = byte;
            }
            Ok(n)
        }
    }

    const LIMITS: AxisLimits = AxisLimits {
        min_mm: 1.0,
        max_mm: 11.0,
        max_speed_mm_s: 2.0,
        acceleration_mm_s2: 4.0,
        command_interval_s: 0.3,
    };

    fn stage(
        silent: bool,
    ) -> (
        Rc<RefCell<SimulatedController>>,
        Result<Axis<SimPort>, AptError>,
    ) {
        let controller = Rc::new(RefCell::new(SimulatedController::new(
            27_000_007,
            ActuatorModel::default(),
        )));
        let port = SimPort {
            controller: controller.clone(),
            written: Vec::new(),
            inbox: VecDeque::new(),
            silent,
        };
        let stage = Axis::connect(port, Z8Units::default(), LIMITS, Duration::from_millis(50)).map(
            |(stage, info)| {
                assert_eq!(info.serial, 27_000_007);
                stage
            },
        );
        (controller, stage)
    }

    fn advance(controller: &Rc<RefCell<SimulatedController>>, seconds: f64) {
        for _ in 0..(seconds * 1000.0).round() as usize {
            controller.borrow_mut().advance(0.001);
        }
    }

    #[test]
    fn moves_at_a_clamped_velocity_and_stops_when_dropped() {
        let (controller, stage) = stage(false);
        let mut stage = stage.unwrap();
        assert_eq!(stage.set_velocity(50.0).unwrap(), Commanded::Moving(2.0));
        advance(&controller, 1.0);
        let position = stage.position_mm().unwrap();
        // 0.5 s accelerating to 2 mm/s (0.5 mm), 0.5 s at 2 mm/s (1 mm).
        assert!((position - 7.5).abs() < 0.01, "{position}");
        assert_eq!(stage.set_velocity(f64::NAN).unwrap(), Commanded::Stopped);
        stage.set_velocity(-1.0).unwrap();
        advance(&controller, 0.2);
        assert!(controller.borrow().status().moving());
        drop(stage);
        assert!(
            !controller.borrow().status().moving(),
            "dropping the driver stops the motor"
        );
    }

    #[test]
    fn motion_toward_a_soft_limit_is_refused_in_time() {
        let (controller, stage) = stage(false);
        let mut stage = stage.unwrap();
        let mut refused = false;
        for _ in 0..100 {
            if stage.set_velocity(2.0).unwrap() == Commanded::Stopped {
                refused = true;
            }
            advance(&controller, 0.3);
        }
        assert!(refused);
        advance(&controller, 2.0);
        let position = stage.position_mm().unwrap();
        assert!(position < LIMITS.max_mm && position > 10.0, "{position}");
        assert_eq!(stage.set_velocity(-2.0).unwrap(), Commanded::Moving(-2.0));
    }

    #[test]
    fn a_silent_controller_times_out() {
        let (_, stage) = stage(true);
        assert!(matches!(stage.unwrap_err(), AptError::Timeout(_)));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]

        /// Whatever velocities are asked for, at whatever intervals up to
        /// the command interval, the stage stays inside its soft limits and
        /// never exceeds its speed limit.
        #[test]
        fn never_past_the_limits(commands in prop::collection::vec((-10.0f64..10.0, 0.05f64..0.3), 1..60)) {
            let (controller, stage) = stage(false);
            let mut stage = stage.unwrap();
            let units = Z8Units::default();
            for (speed, interval) in commands {
                stage.set_velocity(speed).unwrap();
                for _ in 0..(interval * 1000.0).round() as usize {
                    controller.borrow_mut().advance(0.001);
                    let status = controller.borrow().status();
                    let position = units.mm(status.position);
                    prop_assert!((LIMITS.min_mm..=LIMITS.max_mm).contains(&position), "at {position}");
                    let speed = controller.borrow().speed_mm_s().abs();
                    prop_assert!(speed <= LIMITS.max_speed_mm_s + 1e-3, "at {speed} mm/s");
                }
            }
        }
    }

    /// A port that answers each request written to it with the next of
    /// its scripted replies.
    struct Scripted {
        replies: VecDeque<Reply>,
        inbox: VecDeque<u8>,
    }

    impl Scripted {
        fn new(replies: &[Reply]) -> Self {
            Self {
                replies: replies.iter().cloned().collect(),
                inbox: VecDeque::new(),
            }
        }
    }

    impl Write for Scripted {
        fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
            let mut reader = FrameReader::new(bytes);
            while let Ok(frame) = reader.read_frame() {
                let request = matches!(
                    Command::from_frame(&frame),
                    Ok(Command::RequestInfo
                        | Command::RequestEnabled(_)
                        | Command::RequestPosition(_))
                );
                if let Some(reply) = request.then(|| self.replies.pop_front()).flatten() {
                    self.inbox.extend(reply.to_frame().encode());
                }
            }
            Ok(bytes.len())
        }

        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    impl Read for Scripted {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            if self.inbox.is_empty() {
                return Err(ErrorKind::TimedOut.into());
            }
            let n = buf.len().min(self.inbox.len());
            for (slot, byte) in buf.iter_mut().zip(self.inbox.drain(..n)) {
                *slot = byte;
            }
            Ok(n)
        }
    }

    fn info(model: &str) -> Reply {
        Reply::Info(HardwareInfo {
            serial: 27_000_001,
            model: model.into(),
            firmware: "1.0.0".into(),
            hardware_version: 1,
            channels: 1,
            kind: 44,
            notes: String::new(),
        })
    }

    fn connect_to(replies: &[Reply]) -> Result<Axis<Scripted>, AptError> {
        let limits = AxisLimits {
            min_mm: 0.5,
            max_mm: 11.5,
            max_speed_mm_s: 2.0,
            acceleration_mm_s2: 4.0,
            command_interval_s: 0.5,
        };
        let port = Scripted::new(replies);
        Axis::connect(port, Z8Units::default(), limits, Duration::from_millis(20)).map(|(a, _)| a)
    }

    #[test]
    fn another_controller_model_is_refused_at_connect() {
        let err = connect_to(&[info("TDC001")]).err().expect("refused");
        assert!(
            matches!(&err, AptError::Model { model } if model == "TDC001"),
            "{err}"
        );
        assert!(err.to_string().contains("not a KDC101"), "{err}");
    }

    #[test]
    fn a_reply_for_another_channel_is_an_error() {
        let mut axis = connect_to(&[
            info("KDC101"),
            Reply::Enabled(CHANNEL, true),
            Reply::Position(Channel(2), 0),
        ])
        .unwrap();
        let err = axis.position_mm().unwrap_err();
        assert!(err.to_string().contains("channel 2"), "{err}");
    }
}
