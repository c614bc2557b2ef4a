//! The watchdog: a thread that stops both motors when the control loop has
//! not checked in by its deadline (a stalled camera, policy or driver),
//! whatever the loop itself is stuck in.

use kdc101::Stopper;
use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// How often the watchdog looks at the clock.
const POLL: Duration = Duration::from_millis(2);

#[derive(Debug, Default)]
struct WatchdogState {
    deadline: Mutex<Option<Instant>>,
    tripped: AtomicBool,
    quit: AtomicBool,
}

/// A running watchdog; it stops when dropped.
#[derive(Debug)]
pub struct Watchdog {
    shared: Arc<WatchdogState>,
    thread: Option<JoinHandle<()>>,
}

impl Watchdog {
    /// Watches with `stopper` in hand; disarmed until [`Watchdog::arm`].
    pub fn spawn<P: Write + Send + 'static>(stopper: Stopper<P>) -> std::io::Result<Self> {
        let shared = Arc::new(WatchdogState::default());
        let thread = std::thread::Builder::new().name("watchdog".into()).spawn({
            let shared = shared.clone();
            move || {
                while !shared.quit.load(Ordering::Relaxed) {
                    std::thread::sleep(POLL);
                    let mut deadline = shared.deadline.lock().unwrap_or_else(|p| p.into_inner());
                    if deadline.is_some_and(|d| Instant::now() > d) {
                        *deadline = None;
                        // Tripped before the stop goes out: a loop that
                        // checks after each command then never leaves the
                        // motors running after this stop.
                        shared.tripped.store(true, Ordering::SeqCst);
                        let _ = stopper.stop_now();
                        tracing::error!(
                            "watchdog: the control loop missed its deadline; stages stopped"
                        );
                    }
                }
            }
        })?;
        Ok(Self {
            shared,
            thread: Some(thread),
        })
    }

    /// Stops the motors unless re-armed or disarmed before `deadline`.
    pub fn arm(&self, deadline: Instant) {
        *self
            .shared
            .deadline
            .lock()
            .unwrap_or_else(|p| p.into_inner()) = Some(deadline);
    }

    /// Stands down.
    pub fn disarm(&self) {
        *self
            .shared
            .deadline
            .lock()
            .unwrap_or_else(|p| p.into_inner()) = None;
    }

    /// Whether it has stopped the motors since the last call.
    pub fn take_tripped(&self) -> bool {
        self.shared.tripped.swap(false, Ordering::SeqCst)
    }
}

impl Drop for Watchdog {
    fn drop(&mut self) {
        self.shared.quit.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use kdc101::SharedPort;

    #[test]
    fn a_missed_deadline_sends_immediate_stops() {
        let port = SharedPort::new(Vec::<u8>::new());
        let watchdog = Watchdog::spawn(Stopper::new(vec![port.clone(), port.clone()])).unwrap();
        watchdog.arm(Instant::now() + Duration::from_millis(500));
        watchdog.arm(Instant::now() + Duration::from_millis(20));
        std::thread::sleep(Duration::from_millis(100));
        assert!(watchdog.take_tripped());
        assert!(!watchdog.take_tripped());
        drop(watchdog);
        let written = port.with(|bytes| bytes.clone());
        // MOT_STOP (0x0465), channel 1, immediate (1): once per controller.
        let stop = [0x65, 0x04, 0x01, 0x01, 0x50, 0x01];
        assert_eq!(written, [stop, stop].concat());
    }
}
