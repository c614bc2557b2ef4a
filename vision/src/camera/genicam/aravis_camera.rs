//! A GenICam camera through Aravis: connect and configure (every setting
//! read back, a feature the camera lacks refused by name), acquire in
//! free-run or by software trigger, keep incomplete buffers from the loop,
//! and reconnect after the camera was lost.

use super::{Acquisition, CameraInfo, GenicamConfig, GenicamSettings};
use crate::camera::{Camera, CameraError, FrameCounters, GrayFrame, instant_of_unix};
use aravis::prelude::*;
use aravis::{BufferStatus, GvInterface, UvInterface};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Relative disagreement allowed between a float setting and its read-back
/// (cameras round exposure and rate to their clock).
const READ_BACK_TOLERANCE: f64 = 0.02;

/// The longest wait for the first frame after acquisition starts.
const FIRST_FRAME_WAIT: Duration = Duration::from_secs(2);

/// Every camera the GigE Vision and USB3 Vision interfaces find (GigE
/// discovery broadcasts and waits about a second), each opened briefly for
/// its pixel formats.
pub fn discover() -> Vec<CameraInfo> {
    let mut found = Vec::new();
    for interface in [GvInterface::instance(), UvInterface::instance()]
        .into_iter()
        .flatten()
    {
        interface.update_device_list();
        for k in 0..interface.n_devices() {
            let text =
                |v: Option<aravis::glib::GString>| v.map(|s| s.to_string()).unwrap_or_default();
            let id = text(interface.device_id(k));
            found.push(CameraInfo {
                pixel_formats: aravis::Camera::new(Some(&id))
                    .map(|c| pixel_formats(&c))
                    .unwrap_or_default(),
                vendor: text(interface.device_vendor(k)),
                model: text(interface.device_model(k)),
                serial: text(interface.device_serial_nbr(k)),
                address: text(interface.device_address(k)),
                protocol: text(interface.device_protocol(k)),
                id,
            });
        }
    }
    found
}

/// The camera at `name` (an id, serial number or address), opened.
pub fn describe(name: &str) -> Result<CameraInfo, CameraError> {
    let camera = open(name)?;
    let text = |v: Result<aravis::glib::GString, aravis::glib::Error>| {
        v.map(|s| s.to_string()).unwrap_or_default()
    };
    // The id discovery gives, which names the camera in the configuration;
    // the camera's own DeviceID when discovery does not see it.
    let own_id = text(camera.device_id());
    let (id, address) = listed(|interface, k| {
        let (id, address) = (interface.device_id(k)?, interface.device_address(k)?);
        (id == name || address == name || interface.device_serial_nbr(k)?.as_str() == own_id)
            .then(|| (id.to_string(), address.to_string()))
    })
    .unwrap_or_else(|| {
        let address = name
            .parse::<std::net::IpAddr>()
            .is_ok()
            .then(|| name.to_string());
        (own_id.clone(), address.unwrap_or_default())
    });
    Ok(CameraInfo {
        id,
        vendor: text(camera.vendor_name()),
        model: text(camera.model_name()),
        serial: text(camera.device_serial_number()),
        protocol: if camera.is_gv_device() {
            "GigEVision".into()
        } else {
            "USB3Vision".into()
        },
        address,
        pixel_formats: pixel_formats(&camera),
    })
}

fn pixel_formats(camera: &aravis::Camera) -> Vec<String> {
    camera
        .dup_available_pixel_formats_as_strings()
        .map(|v| v.into_iter().map(|s| s.to_string()).collect())
        .unwrap_or_default()
}

/// Opens the camera `name` names: an address directly, else an id, else
/// the camera whose serial number it is; the first camera found when empty.
fn open(name: &str) -> Result<aravis::Camera, CameraError> {
    let unreachable = |e: aravis::glib::Error| {
        CameraError::Device(format!(
            "cannot open the GenICam camera {}: {} (`hardware-agent cameras` lists the cameras found)",
            if name.is_empty() {
                "(the first found)"
            } else {
                name
            },
            e.message()
        ))
    };
    if name.is_empty() || name.parse::<std::net::IpAddr>().is_ok() {
        return aravis::Camera::new((!name.is_empty()).then_some(name)).map_err(unreachable);
    }
    match aravis::Camera::new(Some(name)) {
        Ok(camera) => Ok(camera),
        Err(by_id) => {
            let by_serial = listed(|interface, k| {
                interface
                    .device_serial_nbr(k)
                    .is_some_and(|s| s == name)
                    .then(|| interface.device_id(k))
                    .flatten()
            });
            match by_serial {
                Some(id) => aravis::Camera::new(Some(&id)).map_err(unreachable),
                None => Err(unreachable(by_id)),
            }
        }
    }
}

/// The first answer `find` gives for a camera that discovery finds.
fn listed<T>(find: impl Fn(&aravis::Interface, u32) -> Option<T>) -> Option<T> {
    [GvInterface::instance(), UvInterface::instance()]
        .into_iter()
        .flatten()
        .find_map(|interface| {
            interface.update_device_list();
            (0..interface.n_devices()).find_map(|k| find(&interface, k))
        })
}

/// An open camera and its stream.
struct Link {
    camera: aravis::Camera,
    stream: aravis::Stream,
    /// The stream's count of frames that never arrived, as the current
    /// step began waiting.
    missing_frames: u64,
    /// The pixel format every buffer must carry.
    pixel_format: aravis::PixelFormat,
    acquiring: bool,
}

impl Drop for Link {
    fn drop(&mut self) {
        if self.acquiring {
            let _ = self.camera.stop_acquisition();
        }
    }
}

/// A GenICam camera, configured as `[camera.genicam]` says. It reconnects
/// at the next episode after it was lost.
pub struct GenicamCamera {
    config: GenicamConfig,
    /// The longest wait for a frame.
    timeout: Duration,
    link: Option<Link>,
    settings: GenicamSettings,
    captured: Option<Instant>,
    counters: Arc<FrameCounters>,
}

impl std::fmt::Debug for GenicamCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GenicamCamera")
            .field("settings", &self.settings)
            .field("connected", &self.link.is_some())
            .finish()
    }
}

impl GenicamCamera {
    /// Connects and configures the camera; each grab waits at most
    /// `timeout` for a frame, and `counters` count what arrives.
    pub fn open(
        config: &GenicamConfig,
        timeout: Duration,
        counters: Arc<FrameCounters>,
    ) -> Result<Self, CameraError> {
        config
            .validate()
            .map_err(|e| CameraError::setting("camera.genicam", e))?;
        let (link, settings) = connect(config)?;
        Ok(Self {
            config: config.clone(),
            timeout,
            link: Some(link),
            settings,
            captured: None,
            counters,
        })
    }

    /// The settings the camera took, read back.
    pub fn settings(&self) -> &GenicamSettings {
        &self.settings
    }

    /// Forgets a camera that stopped answering; its teardown, which waits
    /// on the network, runs aside.
    fn lose(&mut self, why: String) -> CameraError {
        if let Some(mut link) = self.link.take() {
            link.acquiring = false;
            let _ = std::thread::Builder::new()
                .name("camera-teardown".into())
                .spawn(move || drop(link));
        }
        CameraError::Device(format!(
            "the GenICam camera {} was lost: {why}; the next episode reconnects",
            self.settings.id
        ))
    }

    /// Triggers an exposure, when frames are triggered by software.
    fn trigger(&mut self) -> Result<(), CameraError> {
        let link = self.link.as_ref().expect("connected");
        if self.config.acquisition == Acquisition::SoftwareTrigger
            && let Err(e) = link.camera.software_trigger()
        {
            return Err(self.lose(format!("the software trigger failed: {}", e.message())));
        }
        Ok(())
    }

    /// Waits until `deadline` for a complete frame, returning incomplete
    /// ones to the camera.
    fn next_frame(&mut self, deadline: Instant) -> Result<GrayFrame, CameraError> {
        let [width, height] = self.size();
        let bytes = self.config.pixel_format.bytes();
        let mut incomplete = 0;
        loop {
            let link = self.link.as_mut().expect("checked by grab");
            let left = deadline.saturating_duration_since(Instant::now());
            let Some(buffer) = link.stream.timeout_pop_buffer(left.as_micros() as u64) else {
                return Err(self.lose(format!(
                    "no complete frame within {:?} ({incomplete} incomplete)",
                    self.timeout
                )));
            };
            let frame = (buffer.status() == BufferStatus::Success
                && buffer.image_pixel_format() == link.pixel_format
                && [buffer.image_width(), buffer.image_height()] == [width as i32, height as i32])
            .then(|| {
                let stride = width * bytes + buffer.image_padding().0.max(0) as usize;
                self.config
                    .pixel_format
                    .frame(&buffer.image_data(), [width, height], stride)
            })
            .flatten();
            let arrived = buffer.system_timestamp();
            link.stream.push_buffer(buffer);
            // In free-run the camera's frames between steps find no
            // buffer by design; only a triggered frame is always wanted.
            if self.config.acquisition == Acquisition::SoftwareTrigger {
                let missing = link.stream.info_uint64_by_name("n_missing_frames");
                self.counters
                    .dropped(missing.saturating_sub(link.missing_frames));
                link.missing_frames = missing;
            }
            match frame {
                Some(frame) => {
                    self.captured = Some(instant_of_unix(Duration::from_nanos(arrived)));
                    return Ok(frame);
                }
                None => {
                    incomplete += 1;
                    self.counters.incomplete();
                }
            }
        }
    }
}

impl Camera for GenicamCamera {
    fn size(&self) -> [usize; 2] {
        let [_, _, w, h] = self.settings.roi;
        [w as usize, h as usize]
    }

    fn grab(&mut self) -> Result<GrayFrame, CameraError> {
        self.start()?;
        let deadline = Instant::now() + self.timeout;
        let link = self.link.as_mut().expect("started");
        // Frames already waiting were captured before this step began.
        while let Some(buffer) = link.stream.try_pop_buffer() {
            link.stream.push_buffer(buffer);
        }
        link.missing_frames = link.stream.info_uint64_by_name("n_missing_frames");
        self.trigger()?;
        let frame = self.next_frame(deadline)?;
        self.counters.frame();
        Ok(frame)
    }

    fn captured(&self) -> Option<Instant> {
        self.captured
    }

    fn start(&mut self) -> Result<(), CameraError> {
        if self.link.is_none() {
            let (link, settings) = connect(&self.config)?;
            if settings.roi != self.settings.roi {
                return Err(CameraError::Device(format!(
                    "the GenICam camera {} came back with a {:?} region, not {:?}",
                    settings.id, settings.roi, self.settings.roi
                )));
            }
            self.link = Some(link);
            self.settings = settings;
        }
        let link = self.link.as_mut().expect("connected");
        if !link.acquiring {
            if let Err(e) = link.camera.start_acquisition() {
                return Err(self.lose(format!("acquisition would not start: {}", e.message())));
            }
            link.acquiring = true;
            // A camera takes a while to send its first frame: wait for it
            // here, not in the first step.
            let deadline = Instant::now() + self.timeout.max(FIRST_FRAME_WAIT);
            self.trigger()?;
            self.next_frame(deadline)?;
        }
        Ok(())
    }

    fn stop(&mut self) {
        if let Some(link) = self.link.as_mut()
            && link.acquiring
        {
            link.acquiring = false;
            if let Err(e) = link.camera.stop_acquisition() {
                let _ = self.lose(format!("acquisition would not stop: {}", e.message()));
            }
        }
    }
}

/// Opens and configures the camera, and reads every setting back.
fn connect(config: &GenicamConfig) -> Result<(Link, GenicamSettings), CameraError> {
    let camera = open(&config.camera)?;
    let id = camera
        .device_id()
        .map(|s| s.to_string())
        .unwrap_or_else(|_| config.camera.clone());
    let refuse = |setting: &str, reason: String| CameraError::Setting {
        setting: format!("camera.genicam.{setting}"),
        reason: format!("camera {id}: {reason}"),
    };
    let failed = |setting: &str, e: aravis::glib::Error| refuse(setting, e.message().to_string());

    let offered = pixel_formats(&camera);
    let format = config.pixel_format.name();
    if !offered.iter().any(|f| f == format) {
        return Err(refuse(
            "pixel_format",
            format!(
                "{format} is not offered; the camera offers {}",
                offered.join(", ")
            ),
        ));
    }
    camera
        .set_pixel_format_from_string(format)
        .map_err(|e| failed("pixel_format", e))?;
    let read_format = camera
        .pixel_format_as_string()
        .map_err(|e| failed("pixel_format", e))?;
    if read_format != format {
        return Err(refuse(
            "pixel_format",
            format!("set to {format}, read back as {read_format}"),
        ));
    }

    let binning = match config.binning {
        Some(want) => {
            if !camera.is_binning_available().unwrap_or(false) {
                return Err(refuse("binning", "the camera has no binning".into()));
            }
            camera
                .set_binning(want[0] as i32, want[1] as i32)
                .map_err(|e| failed("binning", e))?;
            let got = camera.binning().map_err(|e| failed("binning", e))?;
            if [got.0, got.1] != [want[0] as i32, want[1] as i32] {
                return Err(refuse(
                    "binning",
                    format!("set to {want:?}, read back as [{}, {}]", got.0, got.1),
                ));
            }
            Some(want)
        }
        None => camera
            .binning()
            .ok()
            .map(|(x, y)| [x.max(1) as u32, y.max(1) as u32]),
    };

    if let Some([x, y, w, h]) = config.roi {
        if let Ok((sensor_w, sensor_h)) = camera.sensor_size()
            && (u64::from(x) + u64::from(w) > sensor_w.max(0) as u64
                || u64::from(y) + u64::from(h) > sensor_h.max(0) as u64)
        {
            return Err(refuse(
                "roi",
                format!(
                    "{:?} does not fit the {sensor_w} x {sensor_h} px sensor",
                    [x, y, w, h]
                ),
            ));
        }
        camera
            .set_region(x as i32, y as i32, w as i32, h as i32)
            .map_err(|e| failed("roi", e))?;
    }
    let (x, y, w, h) = camera.region().map_err(|e| failed("roi", e))?;
    let roi = [x, y, w, h].map(|v| v.max(0) as u32);
    if let Some(want) = config.roi
        && want != roi
    {
        let steps = [camera.width_increment(), camera.height_increment()]
            .map(|v| v.map(|v| v.to_string()).unwrap_or_else(|_| "?".into()));
        return Err(refuse(
            "roi",
            format!(
                "set to {want:?}, read back as {roi:?} (width in steps of {}, height of {})",
                steps[0], steps[1]
            ),
        ));
    }

    let exposure_us = float_setting(
        config.exposure_us,
        "exposure_us",
        camera.is_exposure_time_available().unwrap_or(false),
        |v| camera.set_exposure_time(v),
        || camera.exposure_time(),
    )
    .map_err(|(setting, reason)| refuse(setting, reason))?;
    let gain = float_setting(
        config.gain,
        "gain",
        camera.is_gain_available().unwrap_or(false),
        |v| camera.set_gain(v),
        || camera.gain(),
    )
    .map_err(|(setting, reason)| refuse(setting, reason))?;

    let frame_rate_hz = match config.acquisition {
        Acquisition::FreeRun => {
            camera
                .clear_triggers()
                .map_err(|e| failed("acquisition", e))?;
            camera
                .set_acquisition_mode(aravis::AcquisitionMode::Continuous)
                .map_err(|e| failed("acquisition", e))?;
            float_setting(
                config.frame_rate_hz,
                "frame_rate_hz",
                camera.is_frame_rate_available().unwrap_or(false),
                |v| camera.set_frame_rate(v),
                || camera.frame_rate(),
            )
            .map_err(|(setting, reason)| refuse(setting, reason))?
        }
        Acquisition::SoftwareTrigger => {
            if camera.is_software_trigger_supported().is_err() {
                return Err(refuse(
                    "acquisition",
                    "the camera has no software trigger (TriggerSoftware); use \"free-run\"".into(),
                ));
            }
            camera
                .set_acquisition_mode(aravis::AcquisitionMode::Continuous)
                .map_err(|e| failed("acquisition", e))?;
            camera
                .set_trigger("Software")
                .map_err(|e| failed("acquisition", e))?;
            None
        }
    };

    let payload = camera.payload().map_err(|e| failed("buffers", e))? as usize;
    let stream = camera.create_stream().map_err(|e| {
        CameraError::Device(format!(
            "camera {id}: cannot open its stream: {}",
            e.message()
        ))
    })?;
    for _ in 0..config.buffers {
        stream.push_buffer(aravis::Buffer::new_allocate(payload));
    }
    let pixel_format = camera
        .pixel_format()
        .map_err(|e| failed("pixel_format", e))?;
    let settings = GenicamSettings {
        id,
        model: camera
            .model_name()
            .map(|s| s.to_string())
            .unwrap_or_default(),
        pixel_format: read_format.to_string(),
        roi,
        binning,
        exposure_us,
        gain,
        frame_rate_hz,
        acquisition: config.acquisition,
    };
    Ok((
        Link {
            missing_frames: stream.info_uint64_by_name("n_missing_frames"),
            camera,
            stream,
            pixel_format,
            acquiring: false,
        },
        settings,
    ))
}

/// Sets a float feature when configured (refused when the camera lacks
/// it) and reads it back; the camera's own value when not configured.
fn float_setting(
    want: Option<f64>,
    name: &'static str,
    available: bool,
    set: impl FnOnce(f64) -> Result<(), aravis::glib::Error>,
    get: impl Fn() -> Result<f64, aravis::glib::Error>,
) -> Result<Option<f64>, (&'static str, String)> {
    let Some(want) = want else {
        return Ok(available.then(|| get().ok()).flatten());
    };
    if !available {
        return Err((name, "the camera does not have this feature".into()));
    }
    set(want).map_err(|e| (name, e.message().to_string()))?;
    let got = get().map_err(|e| (name, e.message().to_string()))?;
    if (got - want).abs() > READ_BACK_TOLERANCE * want.abs().max(1e-9) {
        return Err((name, format!("set to {want}, read back as {got}")));
    }
    Ok(Some(got))
}
