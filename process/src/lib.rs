//! What every process binary of the workspace shares: logging to stderr,
//! how it reports an error, the signals that stop it, and argument
//! parsers.

use nix::sys::signal::{SigSet, Signal};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use tracing_subscriber::EnvFilter;

/// The log filter where `RUST_LOG` is unset: the workspace's crates (all
/// `tweezer_*`) at info, their dependencies at warn. Burn's CUDA kernel
/// compiler logs each pass over each kernel's IR at info: on an H200 a
/// learner's first 35 s wrote 600 MB of it, and the cuda tests ran past a
/// 200 s limit that they meet in 76 s without it.
const DEFAULT_FILTER: &str = "warn,tweezer=info";

/// Logs to stderr, filtered by `RUST_LOG` (default [`DEFAULT_FILTER`]);
/// JSON lines for log collectors when `json`.
pub fn init_logging(json: bool) {
    let filter =
        EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(DEFAULT_FILTER));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()));
    if json {
        builder.json().init();
    } else {
        builder.init();
    }
}

/// How a process binary ends: on an error, `error: ` and the message on
/// stderr, each cause said once, and exit status 1. Never a backtrace,
/// even with `RUST_BACKTRACE` set: a user's mistake is not a crash.
pub fn exit_status(result: anyhow::Result<()>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {}", error_chain(&error));
            ExitCode::FAILURE
        }
    }
}

/// An error and its causes joined by ": ", each said once: a cause whose
/// message the text so far already holds (a wrapper that prints its
/// source) is left out.
pub fn error_chain(error: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in error.chain() {
        let message = cause.to_string();
        if text.contains(&message) {
            continue;
        }
        if !text.is_empty() {
            text.push_str(": ");
        }
        text.push_str(&message);
    }
    text
}

/// SIGINT and SIGTERM (Ctrl-C elsewhere), caught from the moment they are
/// installed: a signal that comes before anything waits for it is kept for
/// [`StopSignals::recv`], not left to the default action that ends the
/// process at once (no checkpoint, stages not stopped).
pub struct StopSignals {
    #[cfg(unix)]
    interrupt: tokio::signal::unix::Signal,
    #[cfg(unix)]
    terminate: tokio::signal::unix::Signal,
    #[cfg(not(unix))]
    ctrl_c: tokio::signal::windows::CtrlC,
}

impl StopSignals {
    /// Catches the stop signals from now on, delivered through `runtime`
    /// (built with I/O enabled). Call it before the process tells anyone
    /// it is up.
    pub fn install(runtime: &tokio::runtime::Handle) -> std::io::Result<Self> {
        let _inside = runtime.enter();
        let caught = || -> std::io::Result<Self> {
            #[cfg(unix)]
            {
                use tokio::signal::unix::{SignalKind, signal};
                Ok(Self {
                    interrupt: signal(SignalKind::interrupt())?,
                    terminate: signal(SignalKind::terminate())?,
                })
            }
            #[cfg(not(unix))]
            {
                Ok(Self {
                    ctrl_c: tokio::signal::windows::ctrl_c()?,
                })
            }
        };
        caught()
            .map_err(|e| std::io::Error::new(e.kind(), format!("cannot catch stop signals: {e}")))
    }

    /// Waits for the next stop signal, or one that came since the last
    /// call; names it. Cancel safe.
    pub async fn recv(&mut self) -> &'static str {
        #[cfg(unix)]
        {
            tokio::select! {
                _ = self.interrupt.recv() => "SIGINT",
                _ = self.terminate.recv() => "SIGTERM",
            }
        }
        #[cfg(not(unix))]
        {
            self.ctrl_c.recv().await;
            "Ctrl-C"
        }
    }
}

/// The SIGHUP catcher [`catch_early_hangups`] installed, until a reload
/// watcher takes over.
static EARLY_HANGUPS: Mutex<Option<(Arc<AtomicBool>, signal_hook::SigId)>> = Mutex::new(None);

/// Catches SIGHUP from now on, for a service that reloads on it: one that
/// comes before the service watches for it (while it loads a checkpoint,
/// say) is remembered for [`early_hangup_came`] instead of ending the
/// process, as the default action would (`systemctl reload` sends SIGHUP
/// whenever it is asked). Call it first thing in a service's `main`.
pub fn catch_early_hangups() {
    let came = Arc::new(AtomicBool::new(false));
    match signal_hook::flag::register(signal_hook::consts::SIGHUP, came.clone()) {
        Ok(id) => {
            *EARLY_HANGUPS
                .lock()
                .unwrap_or_else(|poisoned| poisoned.into_inner()) = Some((came, id));
        }
        Err(e) => {
            eprintln!("cannot catch SIGHUP early ({e}): one sent during start-up ends the process")
        }
    }
    release_hangups();
}

/// Holds SIGHUP pending from now on, across an `exec` that replaces this
/// process with itself (the learner does, to set an allocator option):
/// an exec resets signal handlers but keeps the signal mask, so a SIGHUP
/// sent in between waits for the new image's [`catch_early_hangups`]
/// instead of ending the process. The new image calls that, or
/// [`release_hangups`], before it starts a thread (threads inherit the
/// mask).
pub fn hold_hangups() {
    if let Err(e) = hangups().thread_block() {
        eprintln!("cannot hold SIGHUP ({e}): one sent while the process restarts ends it");
    }
}

/// Lets SIGHUP through again after [`hold_hangups`]; one held meanwhile
/// arrives now. Where nothing was held, it changes nothing.
pub fn release_hangups() {
    if let Err(e) = hangups().thread_unblock() {
        eprintln!("cannot let SIGHUP through ({e})");
    }
}

fn hangups() -> SigSet {
    let mut set = SigSet::empty();
    set.add(Signal::SIGHUP);
    set
}

/// Whether a SIGHUP came since [`catch_early_hangups`]; stops catching
/// them early. Call it once the process watches for SIGHUP itself.
pub fn early_hangup_came() -> bool {
    let caught = EARLY_HANGUPS
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
        .take();
    caught.is_some_and(|(came, id)| {
        signal_hook::low_level::unregister(id);
        came.load(Ordering::SeqCst)
    })
}

/// Parses "X,Y" into two finite numbers (a clap value parser).
pub fn parse_pair(text: &str) -> Result<[f64; 2], String> {
    let parse = |p: &str| {
        p.trim()
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| format!("{p:?} is not a finite number"))
    };
    match text.split(',').collect::<Vec<_>>().as_slice() {
        [x, y] => Ok([parse(x)?, parse(y)?]),
        _ => Err(format!("{text:?}: expected two numbers, X,Y")),
    }
}

#[cfg(test)]
mod tests {
    use super::{
        DEFAULT_FILTER, Signal, StopSignals, catch_early_hangups, early_hangup_came, error_chain,
        hold_hangups, parse_pair,
    };
    use std::io::Write;
    use std::sync::{Arc, Mutex};
    use tracing_subscriber::EnvFilter;

    /// A log writer into a shared buffer.
    #[derive(Clone, Default)]
    struct Buffer(Arc<Mutex<Vec<u8>>>);

    impl Write for Buffer {
        fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(bytes);
            Ok(bytes.len())
        }

        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn a_hangup_held_across_a_restart_reaches_the_early_catcher() {
        hold_hangups();
        // Held: the default action would end this test binary.
        nix::sys::signal::raise(Signal::SIGHUP).unwrap();
        catch_early_hangups();
        assert!(early_hangup_came());
        assert!(!early_hangup_came(), "caught once, then no longer");
    }

    #[test]
    fn by_default_ours_log_at_info_and_dependencies_at_warn() {
        let buffer = Buffer::default();
        let writer = buffer.clone();
        let subscriber = tracing_subscriber::fmt()
            .with_env_filter(EnvFilter::new(DEFAULT_FILTER))
            .with_writer(move || writer.clone())
            .finish();
        tracing::subscriber::with_default(subscriber, || {
            tracing::info!(target: "tweezer_rpc::server", "ours at info");
            tracing::info!(target: "pliron::pass", "a dependency at info");
            tracing::warn!(target: "pliron::pass", "a dependency at warn");
            tracing::warn!(target: "learner", "a binary's own at warn");
        });
        let log = String::from_utf8(buffer.0.lock().unwrap().clone()).unwrap();
        assert!(log.contains("ours at info"), "{log}");
        assert!(!log.contains("a dependency at info"), "{log}");
        assert!(log.contains("a dependency at warn"), "{log}");
        assert!(log.contains("a binary's own at warn"), "{log}");
    }

    #[test]
    fn a_cause_already_in_the_message_is_said_once() {
        let io = std::io::Error::other("x.token: No such file");
        let wrapped = anyhow::Error::new(io).context("cannot read x.token: No such file");
        assert_eq!(error_chain(&wrapped), "cannot read x.token: No such file");
        let plain = anyhow::anyhow!("disk full").context("cannot write the checkpoint");
        assert_eq!(
            error_chain(&plain),
            "cannot write the checkpoint: disk full"
        );
    }

    /// A signal sent before anything waits is kept, and named when asked.
    #[cfg(unix)]
    #[test]
    fn a_stop_signal_before_the_wait_is_kept() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let mut signals = StopSignals::install(runtime.handle()).unwrap();
        let sent = std::process::Command::new("kill")
            .args(["-TERM", &std::process::id().to_string()])
            .status()
            .unwrap();
        assert!(sent.success());
        std::thread::sleep(std::time::Duration::from_millis(100));
        let name = runtime.block_on(async {
            tokio::time::timeout(std::time::Duration::from_secs(10), signals.recv()).await
        });
        assert_eq!(name, Ok("SIGTERM"));
    }

    #[test]
    fn pairs_parse_and_bad_ones_are_named() {
        assert_eq!(parse_pair("1.5, -2"), Ok([1.5, -2.0]));
        assert!(
            parse_pair("1")
                .unwrap_err()
                .contains("expected two numbers")
        );
        assert!(
            parse_pair("1,inf")
                .unwrap_err()
                .contains("\"inf\" is not a finite number")
        );
    }
}
