//! The X and Y stages driven together in image coordinates.

use super::{Calibration, SharedPort, StagesConfig, Stopper};
use crate::apt::{AptError, HardwareInfo, StopMode, Z8Units};
use crate::axis::{Axis, AxisLimits, Commanded};
use crate::serial::open_port;
use serialport::TTYPort;
use std::io::{Read, Write};
use std::path::PathBuf;
use std::time::Duration;

const NAMES: [&str; 2] = ["X", "Y"];

/// A stage that failed.
#[derive(Debug, thiserror::Error)]
pub enum StagesError {
    /// Its serial port cannot be opened.
    #[error("cannot open stage {axis}'s serial port {port}: {source}")]
    Open {
        /// "X" or "Y".
        axis: &'static str,
        /// The port.
        port: PathBuf,
        /// Why.
        source: serialport::Error,
    },
    /// Its port has another controller than the one configured.
    #[error(
        "stage {axis}'s port {port} has controller {found}, but stages.{field} is {expected}: \
         USB serial ports can change names between boots and replugs; name each port by its \
         /dev/serial/by-id/ path (or correct stages.{field})"
    )]
    Serial {
        /// "X" or "Y".
        axis: &'static str,
        /// The port.
        port: PathBuf,
        /// The config field that names the expected serial.
        field: &'static str,
        /// The serial configured.
        expected: u32,
        /// The serial found.
        found: u32,
    },
    /// Its stage has not been homed since its controller powered up.
    #[error(
        "stage {axis} (controller {serial}) has not been homed since its controller powered \
         up: its position counter does not refer to the actuator's travel, so the soft limits \
         would mean nothing. Run `hardware-agent home`, or set stages.require_homed = false \
         if its counter was set another way"
    )]
    NotHomed {
        /// "X" or "Y".
        axis: &'static str,
        /// Its controller's serial number.
        serial: u32,
    },
    /// Its controller failed (its motor has been stopped, unless its port
    /// failed: then the message says it may still be moving).
    #[error("stage {axis}: {source}{}", unreachable_hint(.source))]
    Device {
        /// "X" or "Y".
        axis: &'static str,
        /// What the driver saw.
        source: AptError,
    },
}

/// What a failed port means for the motor behind it: no stop reaches it.
fn unreachable_hint(error: &AptError) -> &'static str {
    match error {
        AptError::Io(_) => {
            ". No stop can reach its controller through this port: if the controller is still \
             powered, its motor may still be moving, up to its limit switch. Stop it at the \
             controller (its front panel, or its power)"
        }
        _ => "",
    }
}

/// Both stages, their calibration, and where they stood when connected
/// (the origin of the trap's world coordinates).
#[derive(Debug)]
pub struct StagePair<P: Read + Write> {
    stages: [Axis<SharedPort<P>>; 2],
    calibration: Calibration,
    origin_mm: [f64; 2],
    limits_mm: [f64; 2],
    stopper: Stopper<P>,
}

impl StagePair<TTYPort> {
    /// Opens the configured serial ports and connects to both controllers;
    /// `command_interval` is the longest time between two commands.
    pub fn open(
        config: &StagesConfig,
        command_interval: Duration,
    ) -> Result<(Self, [HardwareInfo; 2]), StagesError> {
        let open = |axis: usize, port: &PathBuf| {
            open_port(port).map_err(|source| StagesError::Open {
                axis: NAMES[axis],
                port: port.clone(),
                source,
            })
        };
        let ports = [open(0, &config.x_port)?, open(1, &config.y_port)?];
        Self::connect(ports, config, command_interval)
    }

    /// The same on the ports at `paths` (X, Y) instead of the configured
    /// ones (the twin's terminals).
    pub fn open_paths(
        paths: [&std::path::Path; 2],
        config: &StagesConfig,
        command_interval: Duration,
    ) -> Result<(Self, [HardwareInfo; 2]), StagesError> {
        Self::open(
            &StagesConfig {
                x_port: paths[0].to_path_buf(),
                y_port: paths[1].to_path_buf(),
                ..config.clone()
            },
            command_interval,
        )
    }
}

impl<P: Read + Write> StagePair<P> {
    /// Connects to the controllers on `ports` (X, Y).
    pub fn connect(
        ports: [P; 2],
        config: &StagesConfig,
        command_interval: Duration,
    ) -> Result<(Self, [HardwareInfo; 2]), StagesError> {
        let limits = AxisLimits {
            min_mm: config.min_mm,
            max_mm: config.max_mm,
            max_speed_mm_s: config.max_speed_mm_s,
            acceleration_mm_s2: config.acceleration_mm_s2,
            command_interval_s: command_interval.as_secs_f64(),
        };
        let timeout = Duration::from_millis(config.reply_timeout_ms);
        let shared = ports.map(SharedPort::new);
        let stopper = Stopper::new(shared.to_vec());
        let [x, y] = shared;
        let connect = |axis: usize, port| {
            Axis::connect(port, Z8Units::default(), limits, timeout)
                .map(|(stage, info)| {
                    let stage = (stage.with_backlash(config.backlash_um / 1000.0))
                        .with_outside_stops(stopper.stops());
                    (stage, info)
                })
                .map_err(|source| StagesError::Device {
                    axis: NAMES[axis],
                    source,
                })
        };
        let (x, x_info) = connect(0, x)?;
        let (y, y_info) = connect(1, y)?;
        let expected = [
            (config.x_serial, "x_serial", &config.x_port),
            (config.y_serial, "y_serial", &config.y_port),
        ];
        for (axis, (info, (serial, field, port))) in
            [&x_info, &y_info].iter().zip(expected).enumerate()
        {
            if let Some(expected) = serial.filter(|&s| s != info.serial) {
                // Dropping the drivers stops both motors.
                return Err(StagesError::Serial {
                    axis: NAMES[axis],
                    port: port.clone(),
                    field,
                    expected,
                    found: info.serial,
                });
            }
        }
        if config.require_homed {
            for (axis, (stage, info)) in [(&x, &x_info), (&y, &y_info)].into_iter().enumerate() {
                if !stage.homed() {
                    return Err(StagesError::NotHomed {
                        axis: NAMES[axis],
                        serial: info.serial,
                    });
                }
            }
        }
        let mut pair = Self {
            stages: [x, y],
            calibration: config.calibration(),
            origin_mm: [0.0; 2],
            limits_mm: [config.min_mm, config.max_mm],
            stopper,
        };
        pair.origin_mm = pair.position_mm()?;
        Ok((pair, [x_info, y_info]))
    }

    fn each<T>(
        &mut self,
        mut f: impl FnMut(usize, &mut Axis<SharedPort<P>>) -> Result<T, AptError>,
    ) -> Result<[T; 2], StagesError> {
        let mut out = Vec::with_capacity(2);
        for (axis, stage) in self.stages.iter_mut().enumerate() {
            out.push(f(axis, stage).map_err(|source| StagesError::Device {
                axis: NAMES[axis],
                source,
            })?);
        }
        Ok(out
            .try_into()
            .unwrap_or_else(|_| unreachable!("two stages")))
    }

    /// [`Self::each`] for what moves the stages: on an error, both motors
    /// are stopped at once, whatever their drivers managed.
    fn each_or_stop<T>(
        &mut self,
        f: impl FnMut(usize, &mut Axis<SharedPort<P>>) -> Result<T, AptError>,
    ) -> Result<[T; 2], StagesError> {
        let result = self.each(f);
        if result.is_err() {
            let _ = self.stopper.stop_now();
        }
        result
    }

    /// Homes both stages, one after the other, and parks each in the
    /// middle of its soft limits; where they parked (X, Y), mm. The trap's
    /// world origin moves there.
    pub fn home(&mut self) -> Result<[f64; 2], StagesError> {
        let parked = self.each_or_stop(|_, stage| stage.home())?;
        self.origin_mm = self.position_mm()?;
        Ok(parked)
    }

    /// Where the carriages are (X, Y), mm.
    pub fn position_mm(&mut self) -> Result<[f64; 2], StagesError> {
        self.each(|_, stage| stage.carriage_mm())
    }

    /// Where the trap is in world px: its image-axis displacement since
    /// the stages were connected.
    pub fn position_px(&mut self) -> Result<[f64; 2], StagesError> {
        let mm = self.position_mm()?;
        Ok(self.px(mm))
    }

    /// The trap's world px for carriage positions `mm` (X, Y).
    pub fn px(&self, mm: [f64; 2]) -> [f64; 2] {
        self.calibration.px(mm, self.origin_mm)
    }

    /// The world px rectangle (min corner, max corner) the soft travel
    /// limits allow the trap.
    pub fn travel_px(&self) -> [[f64; 2]; 2] {
        let [lo, hi] = self.limits_mm;
        let a = self.calibration.px([lo, lo], self.origin_mm);
        let b = self.calibration.px([hi, hi], self.origin_mm);
        [
            [a[0].min(b[0]), a[1].min(b[1])],
            [a[0].max(b[0]), a[1].max(b[1])],
        ]
    }

    /// Moves the trap at `px_per_s` along the image axes (each stage
    /// clamped and kept inside its limits by its driver). On an error, both
    /// motors are stopped.
    pub fn set_velocity_px(&mut self, px_per_s: [f64; 2]) -> Result<[Commanded; 2], StagesError> {
        self.set_velocity_mm(self.calibration.mm(px_per_s))
    }

    /// Moves each stage (X, Y) at its own speed, mm/s, whatever the
    /// calibration (which `hardware-agent calibrate` is measuring); each is
    /// clamped and kept inside its limits by its driver. On an error, both
    /// motors are stopped.
    pub fn set_velocity_mm(&mut self, mm_s: [f64; 2]) -> Result<[Commanded; 2], StagesError> {
        self.each_or_stop(|axis, stage| stage.set_velocity(mm_s[axis]))
    }

    /// Stops both motors.
    pub fn stop(&mut self, mode: StopMode) -> Result<(), StagesError> {
        self.each_or_stop(|_, stage| stage.stop(mode)).map(|_| ())
    }

    /// A handle that stops both motors from any thread.
    pub fn stopper(&self) -> Stopper<P> {
        self.stopper.clone()
    }
}
