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
//! stale and discarded. A reply a link delivers out of order is caught by
//! the request that brackets every position request. A position outside any
//! Z8 actuator's travel is taken as garbled, never fed to the soft-limit
//! check.
//!
//! Nor does the driver believe a well-formed reading blindly. Frames not
//! addressed from the controller to the host are discarded. Every position
//! is judged against the last: a stage that moved further than the speeds
//! commanded since allow (a runaway motor, a counter that jumped, a
//! controller that reset), or that strays ever further from where the
//! commands sent would have taken it (a frozen encoder, a stalled motor),
//! is stopped and never moved again by this driver. So is one whose controller reports a
//! limit switch, a motion error, a current limit or a disabled channel in
//! any status message it sends, or says that a stage it had homed is no
//! longer homed (it reset).

use crate::apt::{
    AptError, Channel, Command, DEVICE, DcStatus, Direction, FrameReader, HOST, HardwareInfo,
    Reply, StopMode, VelocityParams, Z8Units,
};
use std::io::{ErrorKind, Read, Write};
use std::ops::RangeInclusive;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
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
/// How much faster than commanded a stage may seem to move between two
/// readings (velocity-loop overshoot), as a fraction.
const SPEED_TOLERANCE: f64 = 0.25;
/// Distance two readings may differ beyond what the commanded speeds
/// explain, mm: a few µm of quantisation and profile rounding, well under
/// the 0.5 mm a soft limit usually keeps from the end of travel.
const POSITION_SLACK_MM: f64 = 0.02;
/// Readings that find the stage ever further from where the commands sent
/// would have taken it before the driver takes its encoder as frozen (or
/// its motor stalled or slipping).
const ASTRAY_READINGS: u32 = 2;

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

/// Where the driver reads the time it judges readings by: the wall clock,
/// or a test's simulated one.
#[derive(Clone)]
struct Clock(Arc<dyn Fn() -> Instant + Send + Sync>);

impl Clock {
    fn now(&self) -> Instant {
        (self.0)()
    }
}

impl Default for Clock {
    fn default() -> Self {
        Self(Arc::new(Instant::now))
    }
}

impl std::fmt::Debug for Clock {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Clock")
    }
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
    /// Whether connect has finished: statuses before the channel is
    /// enabled say nothing about a fault.
    connected: bool,
    /// The last position read, to judge the next by.
    last_reading: Option<Reading>,
    /// The fastest the stage may have been commanded to move since that
    /// reading, mm/s.
    fastest_since_read: f64,
    /// Where the commands sent since the last reading that agreed with it
    /// would have taken the motor.
    nominal: Nominal,
    /// Readings since it last agreed that found the stage further from it
    /// than before, and how far off the last of them was, mm.
    astray_readings: u32,
    astray_mm: f64,
    /// Immediate stops sent behind the driver's back (the pair's stopper),
    /// and how many of them the driver has taken into account.
    outside_stops: Option<(Arc<AtomicU64>, u64)>,
    /// Whether one came since the last reading: where the motor stopped
    /// is unknown until the next.
    stopped_outside: bool,
    /// When a stop was sent with no move after it.
    halted_at: Option<Instant>,
    /// The fastest the motor could be moving at `bound_at`, mm/s: a speed
    /// commanded earlier is braked off at the profile's acceleration, not
    /// at once.
    bound_mm_s: f64,
    bound_at: Instant,
    /// Why the driver stopped trusting the stage, once it has.
    untrusted: Option<String>,
    /// Whether the controller reported the stage homed (at connect, or
    /// since [`Axis::home`]): a status that says otherwise is a reset.
    homed: bool,
    /// Homing is under way: the home limit switch is meant to trip.
    homing: bool,
    clock: Clock,
}

/// A position read, and when it was asked for and answered: the
/// controller sampled it in between.
#[derive(Clone, Copy, Debug)]
struct Reading {
    mm: f64,
    asked: Instant,
    answered: Instant,
}

/// Where the motor would be had it followed every command sent exactly:
/// its speed moves toward the one commanded at the profile's acceleration.
#[derive(Clone, Copy, Debug)]
struct Nominal {
    x_mm: f64,
    v_mm_s: f64,
    target_mm_s: f64,
    at: Instant,
    /// Distance covered since the last anchor, mm: how wrong the model
    /// may have grown (within the overshoot allowed).
    travel_mm: f64,
}

impl Nominal {
    fn at_rest(x_mm: f64, at: Instant) -> Self {
        Self {
            x_mm,
            v_mm_s: 0.0,
            target_mm_s: 0.0,
            at,
            travel_mm: 0.0,
        }
    }

    /// Moves the model on to `to`.
    fn advance(&mut self, to: Instant, accel: f64) {
        let dt = to.saturating_duration_since(self.at).as_secs_f64();
        self.at = self.at.max(to);
        let change = self.target_mm_s - self.v_mm_s;
        let ramp = (change.abs() / accel).min(dt);
        let v = self.v_mm_s + change.signum() * accel * ramp;
        let ramp_mm = 0.5 * (self.v_mm_s + v) * ramp;
        let cruise_mm = v * (dt - ramp);
        // A ramp through zero covers both legs.
        let ramp_path = if self.v_mm_s * v < 0.0 {
            (self.v_mm_s * self.v_mm_s + v * v) / (2.0 * accel)
        } else {
            ramp_mm.abs()
        };
        self.x_mm += ramp_mm + cruise_mm;
        self.travel_mm += ramp_path + cruise_mm.abs();
        self.v_mm_s = v;
    }

    /// A velocity command (0: a profiled stop) sent at `now`.
    fn command(&mut self, now: Instant, mm_per_s: f64, accel: f64) {
        self.advance(now, accel);
        self.target_mm_s = mm_per_s;
    }

    /// An immediate stop sent at `now`.
    fn halt(&mut self, now: Instant, accel: f64) {
        self.advance(now, accel);
        self.v_mm_s = 0.0;
        self.target_mm_s = 0.0;
    }

    /// A reading that agreed: the model goes on from there.
    fn anchor(&mut self, x_mm: f64) {
        self.x_mm = x_mm;
        self.travel_mm = 0.0;
    }
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
            connected: false,
            last_reading: None,
            fastest_since_read: 0.0,
            nominal: Nominal::at_rest(0.0, Instant::now()),
            astray_readings: 0,
            astray_mm: 0.0,
            outside_stops: None,
            stopped_outside: false,
            halted_at: None,
            bound_mm_s: 0.0,
            bound_at: Instant::now(),
            untrusted: None,
            homed: false,
            homing: false,
            clock: Clock::default(),
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
        stage.homed = stage.status()?.homed();
        stage.connected = true;
        Ok((stage, info))
    }

    /// Whether the stage has been homed since its controller powered up:
    /// only then do its positions, and so the soft limits, refer to the
    /// actuator's travel.
    pub fn homed(&self) -> bool {
        self.homed
    }

    /// Homes the stage and parks it in the middle of its soft limits; the
    /// position it parked at, mm. Homing runs the motor to its home limit
    /// switch at the controller's homing speed, which zeroes the counter
    /// there; each leg's wait is bounded by the distance it may have to
    /// travel.
    pub fn home(&mut self) -> Result<f64, AptError> {
        self.trusted()?;
        if !self.in_step {
            self.resync()?;
        }
        self.send(Command::RequestHome(CHANNEL))?;
        let Reply::Home(_, params) = self.await_reply(|r| matches!(r, Reply::Home(..)))? else {
            unreachable!("await_reply returns what was asked for")
        };
        let homing_speed = self.units.mm_per_s(params.velocity).abs();
        if homing_speed == 0.0 || !homing_speed.is_finite() {
            return Err(AptError::Unexpected(format!(
                "a homing velocity of {} counts, which never reaches the limit switch: set the \
                 controller's homing velocity (Kinesis: Settings, Home) and home again",
                params.velocity
            )));
        }
        self.homing = true;
        let homed = self.home_and_park(homing_speed);
        self.homing = false;
        if homed.is_err() {
            self.lost_step();
        }
        let park_mm = homed?;
        if !self.status()?.homed() {
            return Err(self.distrust(
                "homing finished, but its controller does not report the stage homed".into(),
            ));
        }
        self.homed = true;
        // Judging starts afresh from the parked stage.
        self.last_reading = None;
        (self.astray_readings, self.astray_mm) = (0, 0.0);
        self.carriage = None;
        self.halted(StopMode::Immediate);
        self.last_speed = 0.0;
        self.bound_mm_s = 0.0;
        Ok(park_mm)
    }

    /// The two legs of [`Axis::home`]: to the limit switch, then to the
    /// middle of the soft limits at the fastest speed allowed.
    fn home_and_park(&mut self, homing_speed: f64) -> Result<f64, AptError> {
        let accel = self.limits.acceleration_mm_s2;
        // Time to travel `mm` at `speed`, with the margin every bound here
        // gives, and a start and stop at the profile's acceleration.
        let leg = |mm: f64, speed: f64| {
            Duration::from_secs_f64(
                (mm / speed + 2.0 * speed / accel) * (1.0 + SPEED_TOLERANCE) + 1.0,
            )
        };
        self.halted(StopMode::Immediate);
        self.send(Command::Home(CHANNEL))?;
        let travel = *PLAUSIBLE_MM.end();
        self.read_reply(
            |r| matches!(r, Reply::Homed(_)),
            Stray::Refuse,
            leg(travel, homing_speed),
        )?;
        let park_mm = 0.5 * (self.limits.min_mm + self.limits.max_mm);
        let speed = self.limits.max_speed_mm_s;
        self.set_speed(self.units.velocity(speed))?;
        self.send(Command::MoveAbsolute(
            CHANNEL,
            Some(self.units.counts(park_mm)),
        ))?;
        self.read_reply(
            |r| matches!(r, Reply::MoveCompleted(_)),
            Stray::Refuse,
            leg(travel, speed),
        )?;
        Ok(park_mm)
    }

    /// The controller's status, asked for now.
    fn status(&mut self) -> Result<DcStatus, AptError> {
        self.send(Command::RequestStatus(CHANNEL))?;
        match self.await_reply(|r| matches!(r, Reply::Status(_)))? {
            Reply::Status(status) => Ok(status),
            _ => unreachable!("await_reply returns what was asked for"),
        }
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

    /// Counts the immediate stops sent to this controller from elsewhere
    /// (the count `stops` keeps): the driver takes each as having stopped
    /// the motor, somewhere, rather than as a stage gone astray.
    pub fn with_outside_stops(mut self, stops: Arc<AtomicU64>) -> Self {
        let seen = stops.load(Ordering::SeqCst);
        self.outside_stops = Some((stops, seen));
        self
    }

    /// Takes any outside stop sent since the last look into account: the
    /// motor stands still now, where is unknown until the next reading.
    fn notice_outside_stops(&mut self) {
        let Some((stops, seen)) = &mut self.outside_stops else {
            return;
        };
        let count = stops.load(Ordering::SeqCst);
        if count != *seen {
            *seen = count;
            let now = self.clock.now();
            self.nominal.halt(now, self.limits.acceleration_mm_s2);
            self.halted_at.get_or_insert(now);
            self.stopped_outside = true;
        }
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
        self.trusted()?;
        if !self.in_step {
            self.resync()?;
        }
        let asked = self.clock.now();
        let counts = self.bracketed_position()?;
        let answered = self.clock.now();
        let mm = self.units.mm(counts);
        if !PLAUSIBLE_MM.contains(&mm) {
            self.lost_step();
            return Err(AptError::Unexpected(format!(
                "a position of {mm:.3} mm, outside any Z8 actuator's travel: a garbled reply"
            )));
        }
        self.judge(Reading {
            mm,
            asked,
            answered,
        })?;
        Ok(mm)
    }

    /// Asks for the position, then for the channel's enable state, and
    /// takes the position only if exactly one came before that answer. A
    /// position reply carries nothing to tell which request it answers:
    /// one that comes late, after its request timed out and the driver got
    /// back in step (from a controller or a link that reorders replies),
    /// makes two, in this bracket or the next, and is never taken for the
    /// fresh one.
    fn bracketed_position(&mut self) -> Result<i32, AptError> {
        self.send(Command::RequestPosition(CHANNEL))?;
        self.send(Command::RequestEnabled(CHANNEL))?;
        let mut positions = Vec::with_capacity(1);
        let enabled = loop {
            match self.await_reply(|r| matches!(r, Reply::Position(..) | Reply::Enabled(..)))? {
                Reply::Position(_, counts) => positions.push(counts),
                Reply::Enabled(_, enabled) => break enabled,
                _ => unreachable!("await_reply returns what was asked for"),
            }
        };
        if !enabled {
            return Err(self.distrust("its channel is disabled".into()));
        }
        let what = match positions[..] {
            [counts] => return Ok(counts),
            [] => "no position reply before the answer to the request after it".to_string(),
            _ => format!("{} position replies to one request", positions.len()),
        };
        self.lost_step();
        Err(AptError::Unexpected(format!(
            "{what}: the controller or its link lost a reply or sent one late, out of order; \
             no position is used until the driver is back in step"
        )))
    }

    /// Judges a reading by the last: the stage cannot have moved further
    /// than the fastest speed commanded since allows (until a stop, then
    /// its braking distance), nor stray ever further from where the
    /// commands sent would have taken it.
    fn judge(&mut self, reading: Reading) -> Result<(), AptError> {
        let mut agreed = true;
        if let Some(last) = self.last_reading {
            let fastest = self.fastest_since_read;
            // The controller sampled each reading between its request
            // and its reply: this bounds the time between the two.
            let end = self
                .halted_at
                .map_or(reading.answered, |t| t.max(last.asked));
            let window = end.saturating_duration_since(last.asked).as_secs_f64();
            let braking = if self.halted_at.is_some() {
                fastest * fastest / (2.0 * self.limits.acceleration_mm_s2)
            } else {
                0.0
            };
            let allowed =
                (fastest * window + braking) * (1.0 + SPEED_TOLERANCE) + POSITION_SLACK_MM;
            let moved = reading.mm - last.mm;
            if moved.abs() > allowed {
                return Err(self.distrust(format!(
                    "its position went from {:.4} mm to {:.4} mm within {:.0} ms: {:.4} mm, \
                     where the {fastest:.3} mm/s commanded allow at most {allowed:.4} mm \
                     (a runaway motor, a counter that jumped, or a controller that reset)",
                    last.mm,
                    reading.mm,
                    1000.0 * reading.answered.duration_since(last.asked).as_secs_f64(),
                    moved.abs(),
                )));
            }
            self.notice_outside_stops();
            // Where the commands would have taken it, sampled between
            // request and reply, give or take the overshoot allowed.
            let accel = self.limits.acceleration_mm_s2;
            let slack = POSITION_SLACK_MM + SPEED_TOLERANCE * self.nominal.travel_mm;
            let [a, b] = [reading.asked, reading.answered].map(|t| {
                self.nominal.advance(t, accel);
                self.nominal.x_mm
            });
            let (lo, hi) = (a.min(b) - slack, a.max(b) + slack);
            let off = (lo - reading.mm).max(reading.mm - hi).max(0.0);
            agreed = off == 0.0 || self.stopped_outside;
            if agreed {
                (self.astray_readings, self.astray_mm) = (0, 0.0);
            } else if off > self.astray_mm + POSITION_SLACK_MM {
                // Further off than last time: a command that reached the
                // controller late leaves a constant offset, a counter
                // that does not follow the motor a growing one.
                (self.astray_readings, self.astray_mm) = (self.astray_readings + 1, off);
                if self.astray_readings >= ASTRAY_READINGS {
                    return Err(self.distrust(format!(
                        "the velocities commanded would have taken it to {:.4}–{:.4} mm, but \
                         its position read {:.4} mm, further off at {ASTRAY_READINGS} readings \
                         (a frozen encoder, or a stalled or slipping motor)",
                        lo + slack,
                        hi - slack,
                        reading.mm
                    )));
                }
            }
        }
        if self.last_reading.is_none() {
            self.nominal = Nominal::at_rest(reading.mm, reading.answered);
        }
        self.last_reading = Some(reading);
        self.fastest_since_read = self.speed_bound(reading.asked);
        if agreed {
            // Model errors start afresh from here.
            self.nominal.anchor(reading.mm);
        }
        self.stopped_outside = false;
        Ok(())
    }

    /// The fastest the motor can be moving at `now`, mm/s: the last speed
    /// commanded, or a faster one before it less what braking at the
    /// profile's acceleration has taken off since.
    fn speed_bound(&self, now: Instant) -> f64 {
        let since = now.saturating_duration_since(self.bound_at).as_secs_f64();
        let braked = self.bound_mm_s - self.limits.acceleration_mm_s2 * since;
        braked.max(self.last_speed)
    }

    /// Stops the motor at once and stops trusting the stage, for `why`;
    /// the error to return.
    fn distrust(&mut self, why: String) -> AptError {
        self.lost_step();
        self.untrusted.get_or_insert(why.clone());
        AptError::Untrusted(why)
    }

    /// The error that ended the driver's trust, if one has.
    fn trusted(&self) -> Result<(), AptError> {
        match &self.untrusted {
            Some(why) => Err(AptError::Untrusted(why.clone())),
            None => Ok(()),
        }
    }

    /// Moves at `mm_per_s` (sign = direction) until the next command,
    /// within the limits: the speed is clamped, and motion toward a soft
    /// limit the stage could pass before the next command is refused with
    /// a profiled stop. A non-finite speed stops the stage.
    pub fn set_velocity(&mut self, mm_per_s: f64) -> Result<Commanded, AptError> {
        if let Err(e) = self.trusted() {
            let _ = self.stop(StopMode::Immediate);
            return Err(e);
        }
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
        // The stage may still be moving faster: bound the travel by that,
        // and by the overshoot a reading is allowed before it is a fault.
        let fastest = speed.abs().max(self.speed_bound(self.clock.now())) * (1.0 + SPEED_TOLERANCE);
        // A frozen encoder hides motion for up to ASTRAY_READINGS readings
        // before it is found: the margin covers that travel too.
        let intervals = 1.0 + f64::from(ASTRAY_READINGS);
        let reach = fastest * self.limits.command_interval_s * intervals
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
        self.set_speed(self.units.velocity(speed.abs()))?;
        self.send(Command::MoveVelocity(CHANNEL, direction))?;
        let (speed_abs, now) = (speed.abs(), self.clock.now());
        self.notice_outside_stops();
        self.nominal
            .command(now, speed, self.limits.acceleration_mm_s2);
        self.bound_mm_s = self.speed_bound(now).max(speed_abs);
        self.bound_at = now;
        self.fastest_since_read = self.fastest_since_read.max(speed_abs);
        self.halted_at = None;
        self.last_speed = speed_abs;
        Ok(Commanded::Moving(speed))
    }

    /// Sets the velocity profile's top speed (device units) at the
    /// configured acceleration, unless the controller has it already.
    fn set_speed(&mut self, units: i32) -> Result<(), AptError> {
        if self.speed_set != Some(units) {
            let params = VelocityParams {
                min_velocity: 0,
                acceleration: self.units.acceleration(self.limits.acceleration_mm_s2),
                max_velocity: units,
            };
            self.send(Command::SetVelocity(CHANNEL, params))?;
            self.speed_set = Some(units);
        }
        Ok(())
    }

    /// Stops the motor. A stop is never refused, whatever the driver
    /// thinks of the stage.
    pub fn stop(&mut self, mode: StopMode) -> Result<(), AptError> {
        self.halted(mode);
        self.send(Command::Stop(CHANNEL, mode))
    }

    /// Notes that a stop is being sent: the stage slows from here on, at
    /// once or along the profile.
    fn halted(&mut self, mode: StopMode) {
        self.notice_outside_stops();
        let now = self.clock.now();
        self.halted_at.get_or_insert(now);
        match mode {
            StopMode::Immediate => self.nominal.halt(now, self.limits.acceleration_mm_s2),
            StopMode::Profiled => self
                .nominal
                .command(now, 0.0, self.limits.acceleration_mm_s2),
        }
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
        let reply = self.read_reply(wanted, Stray::Refuse, self.timeout);
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
        self.halted(StopMode::Immediate);
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
            match self.read_reply(
                |r| matches!(r, Reply::Info(_)),
                Stray::Discard,
                self.timeout,
            ) {
                Ok(Reply::Info(info)) => {
                    if let Some(serial) = self.serial.filter(|&s| s != info.serial) {
                        return Err(AptError::Unexpected(format!(
                            "controller {} answered on the port of controller {serial}",
                            info.serial
                        )));
                    }
                    self.in_step = true;
                    // A controller that reset forgot them: send them
                    // again with the next move.
                    self.speed_set = None;
                    if self.connected {
                        // A reset shows in the status (homing lost).
                        self.status()?;
                    }
                    return Ok(info);
                }
                Ok(_) => unreachable!("read_reply returns what was asked for"),
                Err(e @ (AptError::Io(_) | AptError::Device { .. } | AptError::Untrusted(_))) => {
                    return Err(e);
                }
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

    /// The next reply `wanted` accepts `within` this time. Status messages
    /// the controller sends by itself are skipped; what else comes unasked
    /// (a reply for another channel, another message, garbled bytes) is an
    /// error or discarded, as `stray` says. A controller's error report and
    /// a failed port are errors either way.
    fn read_reply(
        &mut self,
        wanted: impl Fn(&Reply) -> bool,
        stray: Stray,
        within: Duration,
    ) -> Result<Reply, AptError> {
        let refuse = stray == Stray::Refuse;
        let deadline = Instant::now() + within;
        loop {
            // Meant for another device, or from one: not an answer.
            let frame = (self.io.read_frame())
                .map(|frame| (frame.addresses() == (HOST, DEVICE)).then_some(frame));
            match frame.and_then(|f| f.as_ref().map(Reply::from_frame).transpose()) {
                Ok(None) => {}
                Ok(Some(reply)) => {
                    if let Reply::Status(status)
                    | Reply::MoveStopped(status)
                    | Reply::MoveCompleted(status) = &reply
                    {
                        self.inspect(status)?;
                    }
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
                return Err(AptError::Timeout(within));
            }
        }
    }

    /// A status the controller sent: once connected, a limit switch, a
    /// motion error, a current limit, a disabled channel or a homed stage
    /// no longer homed ends the driver's trust. Homing runs into a limit
    /// switch by design, and is judged by its end instead.
    fn inspect(&mut self, status: &DcStatus) -> Result<(), AptError> {
        if !self.connected || self.homing {
            return Ok(());
        }
        let mut faults = status.faults();
        if self.homed && !status.homed() {
            faults.push(
                "it is no longer homed (its controller reset): its counter no longer refers \
                 to the actuator's travel",
            );
        }
        if faults.is_empty() {
            return Ok(());
        }
        Err(self.distrust(format!(
            "{} (status bits 0x{:08x})",
            faults.join(", "),
            status.bits
        )))
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
    use crate::simulator::{ActuatorModel, Malfunction, SimulatedController};
    use proptest::prelude::*;
    use std::collections::VecDeque;
    use std::sync::Mutex;

    /// The simulated controller behind an in-memory port: written frames
    /// are handled at once, replies are read back; an empty inbox times out.
    #[derive(Debug)]
    struct SimPort {
        controller: Arc<Mutex<SimulatedController>>,
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
                    .lock()
                    .unwrap()
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
        Arc<Mutex<SimulatedController>>,
        Result<Axis<SimPort>, AptError>,
    ) {
        let controller = Arc::new(Mutex::new(SimulatedController::new(
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
            |(mut stage, info)| {
                assert_eq!(info.serial, 27_000_007);
                // The driver judges readings by the simulation's time.
                let (base, simulated) = (Instant::now(), controller.clone());
                stage.clock = Clock(Arc::new(move || {
                    base + Duration::from_secs_f64(simulated.lock().unwrap().elapsed_s())
                }));
                stage
            },
        );
        (controller, stage)
    }

    fn advance(controller: &Arc<Mutex<SimulatedController>>, seconds: f64) {
        for _ in 0..(seconds * 1000.0).round() as usize {
            controller.lock().unwrap().advance(0.001);
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
        assert!(controller.lock().unwrap().status().moving());
        drop(stage);
        assert!(
            !controller.lock().unwrap().status().moving(),
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
        // It stops short by at most the margin at 2 mm/s: three command
        // intervals (this one, and two a frozen encoder may hide) and the
        // braking distance, at 1.25× the speed.
        let fastest = 2.0 * (1.0 + SPEED_TOLERANCE);
        let margin = fastest * 0.3 * 3.0 + fastest * fastest / 8.0;
        assert!(
            position < LIMITS.max_mm && position > LIMITS.max_mm - margin - 0.1,
            "{position}"
        );
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
                    controller.lock().unwrap().advance(0.001);
                    let status = controller.lock().unwrap().status();
                    let position = units.mm(status.position);
                    prop_assert!((LIMITS.min_mm..=LIMITS.max_mm).contains(&position), "at {position}");
                    let speed = controller.lock().unwrap().speed_mm_s().abs();
                    prop_assert!(speed <= LIMITS.max_speed_mm_s + 1e-3, "at {speed} mm/s");
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// The same, with the hardware failing at a random command: a
        /// motor that runs faster than told by as much as a reading may
        /// show before it is a fault, a counter that jumps, a frozen
        /// encoder, or a power cycle. The motor never passes a soft limit,
        /// and once the driver has refused a move it never moves the motor
        /// again.
        #[test]
        fn never_past_the_limits_whatever_fails(
            commands in prop::collection::vec((-10.0f64..10.0, 0.05f64..0.3), 1..60),
            at in 0usize..60,
            fault in 0usize..4,
            jump in -8.0f64..8.0,
        ) {
            let (controller, stage) = stage(false);
            let mut stage = stage.unwrap();
            // Read once before anything fails, as the stage pair does at
            // connect: a counter wrong from the first reading on can only
            // be found by homing.
            stage.position_mm().unwrap();
            let mut refused = false;
            for (k, (speed, interval)) in commands.into_iter().enumerate() {
                if k == at {
                    let mut c = controller.lock().unwrap();
                    match fault {
                        0 => c.set_malfunction(Some(Malfunction::Runaway(1.0 + SPEED_TOLERANCE))),
                        1 => c.jump_counter(jump),
                        2 => c.set_malfunction(Some(Malfunction::FrozenEncoder)),
                        _ => c.power_cycle(),
                    }
                }
                let before = controller.lock().unwrap().carriage_mm();
                let commanded = stage.position_mm().and_then(|_| stage.set_velocity(speed));
                if refused {
                    prop_assert!(commanded.is_err());
                }
                refused |= matches!(commanded, Err(AptError::Untrusted(_)));
                for _ in 0..(interval * 1000.0).round() as usize {
                    controller.lock().unwrap().advance(0.001);
                    let motor = controller.lock().unwrap().carriage_mm();
                    prop_assert!((LIMITS.min_mm..=LIMITS.max_mm).contains(&motor), "at {motor}");
                }
                if refused {
                    let after = controller.lock().unwrap().carriage_mm();
                    let moving = controller.lock().unwrap().speed_mm_s();
                    prop_assert!(moving == 0.0 || (after - before).abs() < 1.0);
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
                        | Command::RequestStatus(_)
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
            Reply::Status(DcStatus {
                channel: CHANNEL,
                position: 0,
                velocity: 0,
                bits: 0x8000_0400,
            }),
            Reply::Position(Channel(2), 0),
        ])
        .unwrap();
        let err = axis.position_mm().unwrap_err();
        assert!(err.to_string().contains("channel 2"), "{err}");
    }
}
