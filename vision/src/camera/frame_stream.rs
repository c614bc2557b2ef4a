//! Frames from any program: a camera whose only driver is a vendor SDK
//! (Thorlabs' uc480/TSI, Hamamatsu DCAM, Micro-Manager) is fed to the agent
//! by a short script that writes binary PGM frames, one after another,
//! either on its standard output (the agent starts it: `command`) or into a
//! Unix socket the agent listens on (`socket`).
//!
//! The format is binary PGM (netpbm's P5), so any image tool reads a
//! recorded stream: `P5`, whitespace, width, height and the largest pixel
//! value as decimal text separated by whitespace, one whitespace byte, then
//! the pixels row by row, one byte each when the largest value is below
//! 256, else two, most significant first. A comment line `# captured=T` in
//! the header, T in Unix seconds, says when the frame was exposed; the
//! loop's latency then counts from there.

use super::{Camera, CameraError, FrameCounters, GrayFrame, instant_of_unix};
use serde::{Deserialize, Serialize};
use std::io::{BufRead, BufReader, Read};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tweezer_config::{ConfigError, in_range};

/// The longest PGM header read before the stream is declared malformed.
const MAX_HEADER_BYTES: usize = 4096;
/// The most pixels a frame may have (a 64-megapixel sensor).
const MAX_PIXELS: usize = 64 << 20;
/// How often the socket's listener checks whether it should stop.
const ACCEPT_POLL: Duration = Duration::from_millis(50);

/// The `[camera.stream]` table: where the frames come from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StreamConfig {
    /// A program and its arguments: the agent starts it and reads frames
    /// from its standard output (its standard error goes to the agent's
    /// log). Restarted at the next episode when it dies, stalls or writes
    /// a malformed frame.
    pub command: Vec<String>,
    /// Or a Unix socket the agent listens on; a program connects and
    /// writes frames, and a newer connection replaces an older one.
    pub socket: Option<PathBuf>,
    /// The longest wait for the first frame when the camera starts, s
    /// (a camera SDK may take seconds to open).
    pub start_timeout_s: f64,
}

impl Default for StreamConfig {
    fn default() -> Self {
        Self {
            command: Vec::new(),
            socket: None,
            start_timeout_s: 10.0,
        }
    }
}

impl StreamConfig {
    /// Checks the table; the error names what is wrong.
    pub fn validate(&self) -> Result<(), ConfigError> {
        match (self.command.is_empty(), &self.socket) {
            (true, None) => {
                return Err(ConfigError::invalid(
                    "command",
                    "set `command` (a program writing frames on its standard output) or `socket` (a Unix socket path)",
                ));
            }
            (false, Some(_)) => {
                return Err(ConfigError::invalid(
                    "socket",
                    "set `command` or `socket`, not both",
                ));
            }
            _ => {}
        }
        in_range("start_timeout_s", self.start_timeout_s, 0.1, 600.0)
    }
}

/// One frame read from a stream, and when it was exposed if it says.
#[derive(Debug)]
pub struct StreamFrame {
    /// The pixels.
    pub frame: GrayFrame,
    /// When it was exposed (Unix time), from a `# captured=` comment.
    pub captured_unix: Option<Duration>,
}

/// Why no frame could be read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PgmError {
    /// The stream stopped partway through a frame, at the place named: its
    /// writer died or closed it, which is not a fault of the format.
    Cut(String),
    /// The bytes are not a binary PGM frame; the text says why.
    Malformed(String),
}

impl std::fmt::Display for PgmError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PgmError::Cut(place) => write!(f, "the stream ended {place}"),
            PgmError::Malformed(why) => f.write_str(why),
        }
    }
}

/// Reads the next frame; `Ok(None)` when the stream ends between frames.
pub fn read_pgm(reader: &mut impl BufRead) -> Result<Option<StreamFrame>, PgmError> {
    let malformed = PgmError::Malformed;
    let mut header = Header::default();
    let mut fields = Vec::with_capacity(4);
    let mut token = Vec::new();
    let mut comment: Option<Vec<u8>> = None;
    while fields.len() < 4 {
        let mut byte = [0u8];
        let read = reader
            .read(&mut byte)
            .map_err(|e| PgmError::Cut(format!("with a read error ({e})")))?;
        if read == 0 {
            if header.bytes == 0 {
                return Ok(None);
            }
            return Err(PgmError::Cut("inside a frame's header".into()));
        }
        header.bytes += 1;
        if header.bytes > MAX_HEADER_BYTES {
            return Err(malformed(format!(
                "a header longer than {MAX_HEADER_BYTES} bytes"
            )));
        }
        let b = byte[0];
        if let Some(text) = comment.as_mut() {
            if b == b'\n' || b == b'\r' {
                header.comment(text);
                comment = None;
            } else {
                text.push(b);
            }
            continue;
        }
        if b.is_ascii_whitespace() || b == b'#' {
            if !token.is_empty() {
                fields.push(std::mem::take(&mut token));
            }
            if b == b'#' {
                comment = Some(Vec::new());
            }
            continue;
        }
        token.push(b);
    }
    if fields[0] != b"P5" {
        return Err(malformed(format!(
            "a frame must start with P5 (binary PGM), not {:?}",
            String::from_utf8_lossy(&fields[0])
        )));
    }
    let number = |k: usize, name: &str| -> Result<usize, PgmError> {
        std::str::from_utf8(&fields[k])
            .ok()
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| {
                malformed(format!(
                    "the {name} {:?} is not a number",
                    String::from_utf8_lossy(&fields[k])
                ))
            })
    };
    let (width, height, max_value) = (
        number(1, "width")?,
        number(2, "height")?,
        number(3, "largest value")?,
    );
    if width == 0 || height == 0 || width.saturating_mul(height) > MAX_PIXELS {
        return Err(malformed(format!(
            "a {width} x {height} px frame (at most {MAX_PIXELS} px)"
        )));
    }
    if !(1..=65535).contains(&max_value) {
        return Err(malformed(format!(
            "the largest value {max_value} is not in 1..=65535"
        )));
    }
    let wide = max_value > 255;
    let mut raster = vec![0u8; width * height * if wide { 2 } else { 1 }];
    reader
        .read_exact(&mut raster)
        .map_err(|e| PgmError::Cut(format!("inside a {width} x {height} px frame ({e})")))?;
    let pixels: Vec<u16> = if wide {
        raster
            .chunks_exact(2)
            .map(|b| u16::from_be_bytes([b[0], b[1]]))
            .collect()
    } else {
        raster.into_iter().map(u16::from).collect()
    };
    let frame = GrayFrame::new(width, height, max_value as u16, pixels)
        .ok_or_else(|| malformed(format!("a pixel exceeds the largest value {max_value}")))?;
    Ok(Some(StreamFrame {
        frame,
        captured_unix: header.captured,
    }))
}

/// What a header's comments said.
#[derive(Default)]
struct Header {
    bytes: usize,
    captured: Option<Duration>,
}

impl Header {
    fn comment(&mut self, text: &[u8]) {
        let text = String::from_utf8_lossy(text);
        if let Some(value) = text.trim().strip_prefix("captured=") {
            self.captured = value
                .trim()
                .parse::<f64>()
                .ok()
                .and_then(|s| Duration::try_from_secs_f64(s).ok());
        }
    }
}

/// The newest frame a feed delivered, shared between its reader thread and
/// the camera.
#[derive(Default)]
struct Mailbox {
    state: Mutex<Mail>,
    arrived: Condvar,
}

#[derive(Default)]
struct Mail {
    /// Frames delivered so far.
    sequence: u64,
    latest: Option<(GrayFrame, Instant)>,
    /// Why the feed ended, once it has.
    ended: Option<String>,
}

impl Mailbox {
    fn lock(&self) -> MutexGuard<'_, Mail> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn deliver(&self, frame: StreamFrame) {
        let arrived = frame
            .captured_unix
            .map(instant_of_unix)
            .unwrap_or_else(Instant::now);
        let mut mail = self.lock();
        mail.sequence += 1;
        mail.latest = Some((frame.frame, arrived));
        self.arrived.notify_all();
    }

    fn end(&self, why: String) {
        let mut mail = self.lock();
        mail.ended.get_or_insert(why);
        self.arrived.notify_all();
    }

    /// Reads frames from `input` until it ends or errs.
    fn read_from(&self, input: impl Read, counters: &FrameCounters, source: &str) {
        let mut input = BufReader::with_capacity(1 << 20, input);
        loop {
            match read_pgm(&mut input) {
                Ok(Some(frame)) => self.deliver(frame),
                Ok(None) => return self.end(format!("{source} closed its stream")),
                Err(e) => {
                    counters.incomplete();
                    return self.end(match e {
                        PgmError::Cut(place) => format!("{source} closed its stream {place}"),
                        PgmError::Malformed(why) => {
                            format!("{source} wrote a malformed frame: {why}")
                        }
                    });
                }
            }
        }
    }
}

/// Where frames are coming from now.
enum Feed {
    /// A program the agent started.
    Program { child: Child, mailbox: Arc<Mailbox> },
    /// Connections to the socket.
    Socket(Arc<Mailbox>),
}

/// The socket's listener: it hands each connection to a reader thread of
/// the current mailbox, and a newer connection closes the older one.
struct SocketListener {
    path: PathBuf,
    current: Arc<Mutex<(Arc<Mailbox>, Option<UnixStream>)>>,
    stop: Arc<std::sync::atomic::AtomicBool>,
}

impl Drop for SocketListener {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        let _ = std::fs::remove_file(&self.path);
    }
}

impl SocketListener {
    fn bind(path: &Path, counters: Arc<FrameCounters>) -> Result<Self, CameraError> {
        let error = |e: std::io::Error| {
            CameraError::Device(format!("cannot listen on {}: {e}", path.display()))
        };
        // A socket left by an agent that died is replaced; any other file
        // is not.
        if let Ok(meta) = std::fs::symlink_metadata(path) {
            use std::os::unix::fs::FileTypeExt;
            if !meta.file_type().is_socket() {
                return Err(CameraError::Device(format!(
                    "camera.stream.socket: {} exists and is not a socket",
                    path.display()
                )));
            }
            std::fs::remove_file(path).map_err(error)?;
        }
        let listener = UnixListener::bind(path).map_err(error)?;
        listener.set_nonblocking(true).map_err(error)?;
        let current = Arc::new(Mutex::new((Arc::new(Mailbox::default()), None)));
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (shared, stopping) = (current.clone(), stop.clone());
        let shown = path.display().to_string();
        std::thread::Builder::new()
            .name("frame-socket".into())
            .spawn(move || {
                while !stopping.load(std::sync::atomic::Ordering::Relaxed) {
                    let Ok((stream, _)) = listener.accept() else {
                        std::thread::sleep(ACCEPT_POLL);
                        continue;
                    };
                    let _ = stream.set_nonblocking(false);
                    let Ok(reader) = stream.try_clone() else {
                        continue;
                    };
                    let mailbox = {
                        let mut current = shared.lock().unwrap_or_else(|e| e.into_inner());
                        if let Some(older) = current.1.replace(stream) {
                            let _ = older.shutdown(std::net::Shutdown::Both);
                        }
                        current.0.clone()
                    };
                    let (counters, source) = (counters.clone(), format!("the program on {shown}"));
                    let _ = std::thread::Builder::new()
                        .name("frame-reader".into())
                        .spawn(move || {
                            let mut reader = reader;
                            mailbox.read_from(&mut reader, &counters, &source);
                        });
                }
            })
            .map_err(error)?;
        Ok(Self {
            path: path.to_path_buf(),
            current,
            stop,
        })
    }

    /// The mailbox connections deliver into now.
    fn current(&self) -> Arc<Mailbox> {
        self.current
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .0
            .clone()
    }

    /// Closes the current connection; the next delivers into a fresh
    /// mailbox.
    fn renew(&self) {
        let mut current = self.current.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(stream) = current.1.take() {
            let _ = stream.shutdown(std::net::Shutdown::Both);
        }
        current.0 = Arc::new(Mailbox::default());
    }
}

/// A camera fed by another program, as `[camera.stream]` says.
pub struct StreamCamera {
    config: StreamConfig,
    /// The longest wait for a frame in a step.
    timeout: Duration,
    size: [usize; 2],
    feed: Option<Feed>,
    listener: Option<SocketListener>,
    captured: Option<Instant>,
    counters: Arc<FrameCounters>,
}

impl std::fmt::Debug for StreamCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StreamCamera")
            .field("config", &self.config)
            .field("size", &self.size)
            .field("connected", &self.feed.is_some())
            .finish()
    }
}

impl StreamCamera {
    /// Starts the feed and waits for its first frame, which sets the size
    /// every later frame must have; each grab waits at most `timeout`.
    pub fn open(
        config: &StreamConfig,
        timeout: Duration,
        counters: Arc<FrameCounters>,
    ) -> Result<Self, CameraError> {
        config
            .validate()
            .map_err(|e| CameraError::setting("camera.stream", e))?;
        let listener = config
            .socket
            .as_deref()
            .map(|path| SocketListener::bind(path, counters.clone()))
            .transpose()?;
        let mut camera = Self {
            config: config.clone(),
            timeout,
            size: [0, 0],
            feed: None,
            listener,
            captured: None,
            counters,
        };
        camera.start()?;
        Ok(camera)
    }

    fn mailbox(&self) -> &Arc<Mailbox> {
        match self.feed.as_ref().expect("started") {
            Feed::Program { mailbox, .. } | Feed::Socket(mailbox) => mailbox,
        }
    }

    /// Describes the source, for messages.
    fn source(&self) -> String {
        match &self.config.socket {
            Some(path) => format!("the frame socket {}", path.display()),
            None => format!("the frame program `{}`", self.config.command.join(" ")),
        }
    }

    fn spawn_program(&self) -> Result<Feed, CameraError> {
        let mut child = Command::new(&self.config.command[0])
            .args(&self.config.command[1..])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .map_err(|e| CameraError::Device(format!("cannot start {}: {e}", self.source())))?;
        let stdout = child.stdout.take().expect("piped");
        let mailbox = Arc::new(Mailbox::default());
        let (reader, counters, source) = (mailbox.clone(), self.counters.clone(), self.source());
        std::thread::Builder::new()
            .name("frame-reader".into())
            .spawn(move || reader.read_from(stdout, &counters, &source))
            .map_err(|e| CameraError::Device(format!("cannot read {}: {e}", self.source())))?;
        Ok(Feed::Program { child, mailbox })
    }

    /// Ends the feed, killing its program or closing its connection; the
    /// program's exit status, if it had one.
    fn end_feed(&mut self) -> String {
        if let Some(listener) = &self.listener {
            listener.renew();
        }
        match self.feed.take() {
            Some(Feed::Program { mut child, .. }) => {
                let _ = child.kill();
                child.wait().map(|s| format!(" ({s})")).unwrap_or_default()
            }
            _ => String::new(),
        }
    }

    /// Ends the feed because of `why`; the next episode starts another.
    fn lose(&mut self, why: String) -> CameraError {
        let status = self.end_feed();
        let next = if self.listener.is_some() {
            "waits for the program to connect again"
        } else {
            "restarts it"
        };
        CameraError::Device(format!("{why}{status}; the next episode {next}"))
    }

    /// Refuses a frame of another size than the first, ending the feed.
    fn check_size(&mut self, frame: &GrayFrame) -> Result<(), CameraError> {
        let got = [frame.width(), frame.height()];
        if got == self.size {
            return Ok(());
        }
        self.end_feed();
        Err(CameraError::Size {
            what: format!("from {}", self.source()),
            got,
            want: self.size,
        })
    }

    /// Waits until `deadline` for a frame newer than `after`.
    fn wait_newer(&mut self, after: u64, deadline: Instant) -> Result<GrayFrame, CameraError> {
        let mailbox = self.mailbox().clone();
        let mut mail = mailbox.lock();
        loop {
            if mail.sequence > after
                && let Some((frame, arrived)) = mail.latest.take()
            {
                self.captured = Some(arrived);
                return Ok(frame);
            }
            if let Some(why) = mail.ended.clone() {
                drop(mail);
                return Err(self.lose(why));
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                drop(mail);
                let waited = self.timeout;
                return Err(self.lose(format!("{} sent no frame within {waited:?}", self.source())));
            }
            mail = mailbox
                .arrived
                .wait_timeout(mail, left)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }
}

impl Camera for StreamCamera {
    fn size(&self) -> [usize; 2] {
        self.size
    }

    fn grab(&mut self) -> Result<GrayFrame, CameraError> {
        self.start()?;
        // The first frame to arrive after the step began.
        let after = self.mailbox().lock().sequence;
        let frame = self.wait_newer(after, Instant::now() + self.timeout)?;
        self.check_size(&frame)?;
        self.counters.frame();
        Ok(frame)
    }

    fn captured(&self) -> Option<Instant> {
        self.captured
    }

    fn start(&mut self) -> Result<(), CameraError> {
        if self.feed.is_some() {
            return Ok(());
        }
        self.feed = Some(match &self.listener {
            Some(listener) => Feed::Socket(listener.current()),
            None => self.spawn_program()?,
        });
        let deadline = Instant::now() + Duration::from_secs_f64(self.config.start_timeout_s);
        // Any frame will do: the feed is up. The first sets the size every
        // later frame must have.
        let frame = self.wait_newer(0, deadline)?;
        if self.size == [0, 0] {
            self.size = [frame.width(), frame.height()];
        }
        self.check_size(&frame)
    }
}

impl Drop for StreamCamera {
    fn drop(&mut self) {
        if let Some(Feed::Program { mut child, .. }) = self.feed.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pgm(header: &str, raster: &[u8]) -> Vec<u8> {
        let mut bytes = header.as_bytes().to_vec();
        bytes.extend_from_slice(raster);
        bytes
    }

    #[test]
    fn frames_follow_one_another_with_comments_and_wide_pixels() {
        let mut stream = pgm("P5\n# captured=1700000000.5\n2 1\n255\n", &[7, 9]);
        stream.extend(pgm("P5 1 2 4095 ", &[0x0f, 0xff, 0x01, 0x00]));
        let mut reader = stream.as_slice();
        let first = read_pgm(&mut reader).unwrap().unwrap();
        assert_eq!(first.frame.pixels(), &[7, 9]);
        assert_eq!(
            first.captured_unix,
            Some(Duration::from_secs_f64(1_700_000_000.5))
        );
        let second = read_pgm(&mut reader).unwrap().unwrap();
        assert_eq!(second.frame.pixels(), &[4095, 256]);
        assert_eq!(second.frame.max_value(), 4095);
        assert!(read_pgm(&mut reader).unwrap().is_none());
    }

    #[test]
    fn malformed_frames_say_what_is_wrong() {
        for (bytes, says) in [
            (pgm("P2\n1 1\n255\n", &[0]), "P5"),
            (pgm("P5\n1 x\n255\n", &[0]), "height"),
            (pgm("P5\n0 1\n255\n", &[]), "0 x 1"),
            (pgm("P5\n2 2\n255\n", &[0, 0]), "ended inside a 2 x 2"),
            (pgm("P5\n1 1\n100\n", &[200]), "exceeds"),
            (pgm("P5\n1 1", &[]), "inside a frame's header"),
            (vec![b'#'; 5000], "longer than"),
        ] {
            let error = read_pgm(&mut bytes.as_slice()).unwrap_err().to_string();
            assert!(error.contains(says), "{error} should say {says}");
        }
    }

    #[test]
    fn a_stream_cut_inside_a_frame_is_not_called_malformed() {
        for bytes in [pgm("P5\n2 2\n255\n", &[0, 0]), pgm("P5\n1 1", &[])] {
            let error = read_pgm(&mut bytes.as_slice()).unwrap_err();
            assert!(matches!(error, PgmError::Cut(_)), "{error:?}");
        }
        let garbage = pgm("P2\n1 1\n255\n", &[0]);
        let error = read_pgm(&mut garbage.as_slice()).unwrap_err();
        assert!(matches!(error, PgmError::Malformed(_)), "{error:?}");
    }

    #[test]
    fn a_stream_config_needs_exactly_one_source() {
        assert!(StreamConfig::default().validate().is_err());
        let both = StreamConfig {
            command: vec!["feed".into()],
            socket: Some("/tmp/s".into()),
            ..StreamConfig::default()
        };
        assert!(
            both.validate()
                .unwrap_err()
                .to_string()
                .contains("not both")
        );
    }
}
