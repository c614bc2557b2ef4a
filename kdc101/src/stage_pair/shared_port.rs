//! A serial port shared by a stage's driver and the watchdog that may stop
//! it from another thread: each read or write holds the port for that call
//! only, so a stop frame never lands inside another frame.

use crate::apt::{Command, StopMode};
use crate::axis::CHANNEL;
use std::io::{Read, Write};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

/// A port behind a lock; clones share it.
#[derive(Debug)]
pub struct SharedPort<P>(Arc<Mutex<P>>);

impl<P> Clone for SharedPort<P> {
    fn clone(&self) -> Self {
        Self(self.0.clone())
    }
}

impl<P> SharedPort<P> {
    /// Shares `port`.
    pub fn new(port: P) -> Self {
        Self(Arc::new(Mutex::new(port)))
    }

    /// Runs `f` on the port, holding it.
    pub fn with<T>(&self, f: impl FnOnce(&mut P) -> T) -> T {
        f(&mut self.lock())
    }

    fn lock(&self) -> MutexGuard<'_, P> {
        self.0
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

impl<P: Read> Read for SharedPort<P> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        self.lock().read(buf)
    }
}

impl<P: Write> Write for SharedPort<P> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.lock().write(buf)
    }

    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        self.lock().write_all(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.lock().flush()
    }
}

/// Stops motors from any thread, whatever their drivers are doing.
#[derive(Debug)]
pub struct Stopper<P> {
    ports: Vec<SharedPort<P>>,
    /// Stops sent, for the drivers to tell them from a stalled motor.
    stops: Arc<AtomicU64>,
}

impl<P> Clone for Stopper<P> {
    fn clone(&self) -> Self {
        Self {
            ports: self.ports.clone(),
            stops: self.stops.clone(),
        }
    }
}

impl<P: Write> Stopper<P> {
    /// A stopper for the controllers on `ports`.
    pub fn new(ports: Vec<SharedPort<P>>) -> Self {
        Self {
            ports,
            stops: Arc::new(AtomicU64::new(0)),
        }
    }

    /// The count of stops sent, which rises before each goes out.
    pub fn stops(&self) -> Arc<AtomicU64> {
        self.stops.clone()
    }

    /// Sends an immediate stop to every controller; the first error is
    /// returned after all were tried.
    pub fn stop_now(&self) -> std::io::Result<()> {
        let frame = Command::Stop(CHANNEL, StopMode::Immediate)
            .to_frame()
            .encode();
        self.stops.fetch_add(1, Ordering::SeqCst);
        let mut result = Ok(());
        for port in &self.ports {
            let mut port = port.lock();
            let sent = port.write_all(&frame).and_then(|()| port.flush());
            if result.is_ok() {
                result = sent;
            }
        }
        result
    }
}
