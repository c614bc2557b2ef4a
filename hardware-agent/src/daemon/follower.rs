//! Following a learner's best or latest snapshot: a thread that asks the
//! learner every few seconds and, when it has published a newer snapshot
//! under the tag, downloads and verifies it into a slot. The control thread
//! takes it from the slot between episodes, never during one.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tweezer_gym::EnvConfig;
use tweezer_hardware_agent::policy_source::{LoadedPolicy, PolicyConfig, SnapshotChoice};
use tweezer_rpc::Security;

/// How often the learner is asked.
const POLL: Duration = Duration::from_secs(2);

/// A running follower; dropping it stops the thread.
pub struct Follower {
    tag: SnapshotChoice,
    stop: Arc<AtomicBool>,
    ready: Arc<Mutex<Option<LoadedPolicy>>>,
}

impl Follower {
    /// Follows `tag` of the learner `config` names, from `version` on.
    pub fn spawn(
        tag: SnapshotChoice,
        version: u64,
        config: PolicyConfig,
        env: EnvConfig,
        security: Security,
    ) -> std::io::Result<Self> {
        let stop = Arc::new(AtomicBool::new(false));
        let ready = Arc::new(Mutex::new(None::<LoadedPolicy>));
        let (stopping, slot) = (stop.clone(), ready.clone());
        std::thread::Builder::new()
            .name("policy-follower".into())
            .spawn(move || {
                let mut newest = version;
                let mut failing = false;
                loop {
                    let wake = Instant::now() + POLL;
                    while Instant::now() < wake {
                        if stopping.load(Ordering::Relaxed) {
                            return;
                        }
                        std::thread::sleep(Duration::from_millis(50));
                    }
                    match LoadedPolicy::newer(&config, tag, newest, &env, &security) {
                        Ok(Some(policy)) => {
                            tracing::info!(policy = %policy.description, "following: a newer snapshot is ready for the next episode");
                            newest = policy.version;
                            failing = false;
                            *slot.lock().unwrap_or_else(|p| p.into_inner()) = Some(policy);
                        }
                        Ok(None) => failing = false,
                        Err(e) => {
                            // Said once per outage; the policy in use stays.
                            if !failing {
                                tracing::warn!(error = %e, "following: cannot get the learner's newer snapshot; the current policy stays");
                            }
                            failing = true;
                        }
                    }
                }
            })?;
        Ok(Self { tag, stop, ready })
    }

    /// The tag followed.
    pub fn tag(&self) -> SnapshotChoice {
        self.tag
    }

    /// The newest verified snapshot not yet taken, if any.
    pub fn take(&self) -> Option<LoadedPolicy> {
        self.ready.lock().unwrap_or_else(|p| p.into_inner()).take()
    }
}

impl Drop for Follower {
    /// The thread ends at its next look at the flag: within 50 ms, or
    /// after the download in flight (bounded by `policy.timeout_s`), whose
    /// result nobody takes.
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}
