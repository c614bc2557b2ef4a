//! Where TD3's passes run. On the CPU backend, passes that do not depend on
//! each other run side by side (the TD target and the online critics, Q1
//! and Q2, their backward passes, π and Q1's encoder), and a whole step
//! runs on a rayon worker; elsewhere one after the other on the calling
//! thread, since a GPU runs one pass's kernels in order from one queue
//! (`config::DeviceChoice::device`).

/// How the passes of an update are scheduled on its device.
#[derive(Clone, Copy, Debug)]
pub struct Passes {
    on_cpu: bool,
}

impl Passes {
    /// Scheduling for a device on the CPU backend (`on_cpu`) or not.
    pub fn new(on_cpu: bool) -> Self {
        Self { on_cpu }
    }

    /// Runs `step` on a worker of rayon's global pool on the CPU: the CPU
    /// backend's parallel loops run there. Called from any other thread,
    /// each of those loops (hundreds in an update) is a hand-over to the
    /// pool and a wait for its result; on a worker, the step's own thread
    /// takes part in them.
    pub fn on_worker<R: Send>(self, step: impl FnOnce() -> R + Send) -> R {
        if self.on_cpu {
            rayon::scope(|_| step())
        } else {
            step()
        }
    }

    /// Runs `a` and `b` side by side on the CPU, where the operations of
    /// one pass leave a core idle between them.
    pub fn side_by_side<A: Send, B: Send>(
        self,
        a: impl FnOnce() -> A + Send,
        b: impl FnOnce() -> B + Send,
    ) -> (A, B) {
        if self.on_cpu {
            rayon::join(a, b)
        } else {
            (a(), b())
        }
    }
}
