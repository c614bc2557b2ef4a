//! Requests to end an episode, from any thread, that wake the control loop
//! at once instead of at its next tick.

use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Instant;

/// Why the loop is asked to end.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum HaltKind {
    /// An operator stop: a profiled stop of both stages.
    Stop,
    /// An emergency stop (whoever asked has already stopped the motors).
    Emergency(String),
}

/// A shared, sticky halt request: an emergency outranks a stop.
#[derive(Clone, Debug, Default)]
pub struct Halt(Arc<(Mutex<Option<HaltKind>>, Condvar)>);

impl Halt {
    fn lock(&self) -> MutexGuard<'_, Option<HaltKind>> {
        self.0.0.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Asks the loop to end.
    pub fn request(&self, kind: HaltKind) {
        let mut slot = self.lock();
        if !matches!(*slot, Some(HaltKind::Emergency(_))) {
            *slot = Some(kind);
        }
        self.0.1.notify_all();
    }

    /// The pending request, if any, without clearing it.
    pub fn pending(&self) -> Option<HaltKind> {
        self.lock().clone()
    }

    /// Clears the request (an emergency stop being reset).
    pub fn clear(&self) {
        *self.lock() = None;
    }

    /// Clears a stop request left over from the last episode; an emergency
    /// stop stays.
    pub fn clear_stop(&self) {
        let mut slot = self.lock();
        if *slot == Some(HaltKind::Stop) {
            *slot = None;
        }
    }

    /// Waits until `deadline` unless a request comes first; returns it.
    pub fn wait_until(&self, deadline: Instant) -> Option<HaltKind> {
        let mut slot = self.lock();
        loop {
            if slot.is_some() {
                return slot.clone();
            }
            let now = Instant::now();
            if now >= deadline {
                return None;
            }
            slot = self
                .0
                .1
                .wait_timeout(slot, deadline - now)
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_request_wakes_the_waiter_and_emergencies_stick() {
        let halt = Halt::default();
        let other = halt.clone();
        let asked = Instant::now();
        let waiter =
            std::thread::spawn(move || other.wait_until(Instant::now() + Duration::from_secs(10)));
        std::thread::sleep(Duration::from_millis(20));
        halt.request(HaltKind::Emergency("test".into()));
        assert_eq!(
            waiter.join().unwrap(),
            Some(HaltKind::Emergency("test".into()))
        );
        assert!(asked.elapsed() < Duration::from_secs(5));
        halt.request(HaltKind::Stop);
        halt.clear_stop();
        assert_eq!(halt.pending(), Some(HaltKind::Emergency("test".into())));
        halt.clear();
        halt.request(HaltKind::Stop);
        halt.clear_stop();
        assert_eq!(halt.wait_until(Instant::now()), None);
    }
}
