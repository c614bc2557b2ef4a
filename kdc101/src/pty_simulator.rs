//! A simulated KDC101 served on a pseudo-terminal: the driver opens the
//! terminal's path as it would the controller's USB serial port. The
//! simulation runs in real time on its own thread, replies after a set
//! latency, and can be told to misbehave.

use crate::apt::{AptError, Frame, FrameReader, Reply};
use crate::simulator::{ActuatorModel, SimulatedController};
use nix::fcntl::{FcntlArg, OFlag, fcntl};
use nix::pty::openpty;
use nix::sys::termios::{SetArg, cfmakeraw, tcgetattr, tcsetattr};
use std::fs::File;
use std::io::{ErrorKind, Write};
use std::os::fd::OwnedFd;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// How the simulated controller misbehaves, for tests of the driver.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fault {
    /// It stops replying (it still obeys commands).
    Silent,
    /// It sends only the first half of each reply.
    Truncated,
    /// It replies with a message the driver never asked for.
    Unexpected,
    /// It reports a fault instead of replying: a header-only HW_RESPONSE.
    Failing,
    /// Its replies leave this much later than usual.
    Late(Duration),
    /// Its next position reply leaves this much later than usual, behind
    /// the replies to later requests (a controller answers in order; a
    /// link or a fake that reorders replies does not); then it behaves.
    Straggler(Duration),
}

/// State shared between the server thread and its owner.
#[derive(Debug)]
struct ServerState {
    controller: SimulatedController,
    fault: Option<Fault>,
    /// Bytes to send as they are, ahead of any reply.
    injected: Vec<u8>,
}

/// A simulated KDC101 on a pseudo-terminal; stopped when dropped.
#[derive(Debug)]
pub struct PtySimulator {
    path: PathBuf,
    shared: Arc<Mutex<ServerState>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    // Held open so the terminal survives the driver closing it.
    _slave: OwnedFd,
}

impl PtySimulator {
    /// Opens a pseudo-terminal and serves a controller with serial number
    /// `serial` on it; replies leave `latency` after their command.
    pub fn spawn(serial: u32, model: ActuatorModel, latency: Duration) -> std::io::Result<Self> {
        let pty = openpty(None, None).map_err(std::io::Error::from)?;
        // A serial line, not a terminal: no echo, no line editing, from the
        // start (bytes sent before the driver opens the port included).
        let mut termios = tcgetattr(&pty.slave).map_err(std::io::Error::from)?;
        cfmakeraw(&mut termios);
        tcsetattr(&pty.slave, SetArg::TCSANOW, &termios).map_err(std::io::Error::from)?;
        let path = nix::unistd::ttyname(&pty.slave).map_err(std::io::Error::from)?;
        let flags = fcntl(&pty.master, FcntlArg::F_GETFL).map_err(std::io::Error::from)?;
        fcntl(
            &pty.master,
            FcntlArg::F_SETFL(OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK),
        )
        .map_err(std::io::Error::from)?;
        let shared = Arc::new(Mutex::new(ServerState {
            controller: SimulatedController::new(serial, model),
            fault: None,
            injected: Vec::new(),
        }));
        let stop = Arc::new(AtomicBool::new(false));
        let master = File::from(pty.master);
        let thread = std::thread::Builder::new()
            .name(format!("twin-kdc101-{serial}"))
            .spawn({
                let (shared, stop) = (shared.clone(), stop.clone());
                move || serve(master, &shared, &stop, latency)
            })?;
        Ok(Self {
            path,
            shared,
            stop,
            thread: Some(thread),
            _slave: pty.slave,
        })
    }

    /// The terminal to open as the controller's serial port.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The simulated controller (to read where its carriage is).
    pub fn controller(&self) -> ControllerGuard<'_> {
        ControllerGuard(lock(&self.shared))
    }

    /// Runs `f` on the simulated controller (to make its hardware fail).
    pub fn with_controller<T>(&self, f: impl FnOnce(&mut SimulatedController) -> T) -> T {
        f(&mut lock(&self.shared).controller)
    }

    /// Makes the controller misbehave from now on (or behave again).
    pub fn set_fault(&self, fault: Option<Fault>) {
        lock(&self.shared).fault = fault;
    }

    /// Sends `bytes` down the line as they are (noise, stale bytes).
    pub fn inject(&self, bytes: &[u8]) {
        lock(&self.shared).injected.extend_from_slice(bytes);
    }
}

/// The simulated controller, locked.
pub struct ControllerGuard<'a>(MutexGuard<'a, ServerState>);

impl std::ops::Deref for ControllerGuard<'_> {
    type Target = SimulatedController;
    fn deref(&self) -> &SimulatedController {
        &self.0.controller
    }
}

impl Drop for PtySimulator {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

fn lock(shared: &Mutex<ServerState>) -> MutexGuard<'_, ServerState> {
    shared
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// The server loop: reads commands, advances the simulation in real time,
/// and writes replies when they are due.
fn serve(master: File, shared: &Mutex<ServerState>, stop: &AtomicBool, latency: Duration) {
    let mut reader = FrameReader::new(master);
    let mut due: Vec<(Instant, Vec<u8>)> = Vec::new();
    // Out of order: each leaves when its time comes, whatever is queued.
    let mut stragglers: Vec<(Instant, Vec<u8>)> = Vec::new();
    let mut last = Instant::now();
    while !stop.load(Ordering::Relaxed) {
        loop {
            match reader.read_frame() {
                Ok(frame) => {
                    let mut state = lock(shared);
                    // Brought up to now first: a real controller answers
                    // with where it is when the request arrives.
                    catch_up(&mut state, &mut last, &mut due, latency);
                    // A real controller ignores what it does not understand.
                    let replies = state.controller.handle(&frame).unwrap_or_default();
                    for reply in replies {
                        if let Some(Fault::Straggler(extra)) = state.fault
                            && Reply::from_frame(&reply)
                                .is_ok_and(|r| matches!(r, Reply::Position(..)))
                        {
                            state.fault = None;
                            stragglers.push((Instant::now() + latency + extra, reply.encode()));
                        } else if let Some(bytes) = faulty(state.fault, &reply) {
                            queue(
                                &mut due,
                                Instant::now() + delay(state.fault, latency),
                                bytes,
                            );
                        }
                    }
                }
                // No more bytes now, or no terminal open on the other side.
                Err(AptError::Io(e))
                    if e.kind() == ErrorKind::WouldBlock || e.raw_os_error() == Some(5) =>
                {
                    break;
                }
                Err(_) => break,
            }
        }
        let now = {
            let mut state = lock(shared);
            let now = catch_up(&mut state, &mut last, &mut due, latency);
            if !state.injected.is_empty() {
                let bytes = std::mem::take(&mut state.injected);
                due.insert(0, (now, bytes));
            }
            now
        };
        let port = reader.get_mut();
        for queue in [&mut due, &mut stragglers] {
            queue.retain(|(at, bytes)| {
                if *at > now {
                    return true;
                }
                let _ = port.write_all(bytes);
                false
            });
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// Moves the simulation on from `last` to now, queueing what the
/// controller sends by itself; now.
fn catch_up(
    state: &mut ServerState,
    last: &mut Instant,
    due: &mut Vec<(Instant, Vec<u8>)>,
    latency: Duration,
) -> Instant {
    let now = Instant::now();
    for event in state.controller.advance((now - *last).as_secs_f64()) {
        if let Some(bytes) = faulty(state.fault, &event) {
            queue(due, now + delay(state.fault, latency), bytes);
        }
    }
    *last = now;
    now
}

/// Queues `bytes` to leave at `at`, or after the message queued before
/// them: a controller never reorders its messages.
fn queue(due: &mut Vec<(Instant, Vec<u8>)>, at: Instant, bytes: Vec<u8>) {
    let at = due.last().map_or(at, |(last, _)| at.max(*last));
    due.push((at, bytes));
}

/// How long after its cause a message leaves under `fault`.
fn delay(fault: Option<Fault>, latency: Duration) -> Duration {
    match fault {
        Some(Fault::Late(extra)) => latency + extra,
        _ => latency,
    }
}

/// The bytes a frame goes out as under `fault`, if any.
fn faulty(fault: Option<Fault>, frame: &Frame) -> Option<Vec<u8>> {
    let bytes = frame.encode();
    match fault {
        None | Some(Fault::Late(_) | Fault::Straggler(_)) => Some(bytes),
        Some(Fault::Silent) => None,
        Some(Fault::Truncated) => Some(bytes[..bytes.len() / 2].to_vec()),
        // MOT_MOVE_HOMED: never asked for by the driver.
        Some(Fault::Unexpected) => Some(vec![0x44, 0x04, 0x01, 0x00, 0x01, 0x50]),
        Some(Fault::Failing) => Some(vec![0x80, 0x00, 0x00, 0x00, 0x01, 0x50]),
    }
}
