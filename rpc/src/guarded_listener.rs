//! Every listener's front door. Accepted TCP connections get a bounded TLS
//! handshake (in plaintext: a bound on the first bytes), an idle timeout,
//! and caps on how many may be handshaking and how many may be open. A cap
//! never turns a newcomer away: the connection that matters least makes
//! room instead — the oldest one still handshaking, or, among open ones,
//! the one silent the longest. So silent or slow peers can never lock a
//! client that completes its handshake out (an operator's EmergencyStop
//! included), and accept errors (descriptors exhausted) back off instead of
//! spinning.

use crate::server::current;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock};
use std::task::{Context, Poll, ready};
use std::time::{Duration, Instant};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, oneshot};
use tokio::time::Sleep;
use tokio_rustls::TlsAcceptor;
use tokio_rustls::server::TlsStream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::server::{Connected, TcpConnectInfo};

/// The `[listener]` table of the security file: how every listener of a
/// process (gRPC and metrics) treats connections.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ListenerLimits {
    /// Longest a new connection may take to finish its TLS handshake (or,
    /// in plaintext, to send its first bytes), s.
    pub handshake_timeout_s: f64,
    /// A connection from which nothing arrives for this long is closed, s.
    /// gRPC clients answer the server's keepalive pings (every 30 s), so a
    /// live client never idles out.
    pub idle_timeout_s: f64,
    /// Most connections open at once (past their handshake).
    pub max_connections: usize,
    /// Most connections handshaking at once.
    pub max_handshakes: usize,
}

impl Default for ListenerLimits {
    fn default() -> Self {
        Self {
            handshake_timeout_s: 10.0,
            idle_timeout_s: 300.0,
            max_connections: 512,
            max_handshakes: 64,
        }
    }
}

/// How often the server pings an HTTP/2 client, and how long it waits for
/// the answer before closing the connection.
pub(crate) const KEEPALIVE_INTERVAL: Duration = Duration::from_secs(30);
pub(crate) const KEEPALIVE_TIMEOUT: Duration = Duration::from_secs(20);
/// How long the accept loop rests after an accept error.
const ACCEPT_BACKOFF: Duration = Duration::from_millis(100);
/// Most accept errors logged in one minute.
const LOGGED_ERRORS_PER_MINUTE: u32 = 5;

impl ListenerLimits {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), String> {
        for (name, value, lo, hi) in [
            ("handshake_timeout_s", self.handshake_timeout_s, 0.1, 600.0),
            ("idle_timeout_s", self.idle_timeout_s, 1.0, 86_400.0),
        ] {
            if !(value.is_finite() && (lo..=hi).contains(&value)) {
                return Err(format!(
                    "listener.{name} = {value}: must lie in [{lo}, {hi}]"
                ));
            }
        }
        for (name, value, hi) in [
            ("max_connections", self.max_connections, 100_000),
            ("max_handshakes", self.max_handshakes, 10_000),
        ] {
            if !(1..=hi).contains(&value) {
                return Err(format!("listener.{name} = {value}: must lie in [1, {hi}]"));
            }
        }
        Ok(())
    }

    /// File descriptors a process with `listeners` listeners may hold for
    /// connections at most.
    pub fn descriptors(&self, listeners: usize) -> u64 {
        ((self.max_connections + self.max_handshakes) * listeners) as u64
    }

    fn handshake(&self) -> Duration {
        Duration::from_secs_f64(self.handshake_timeout_s)
    }

    fn idle(&self) -> Duration {
        Duration::from_secs_f64(self.idle_timeout_s)
    }
}

/// A TLS server configuration that a reload may replace; new handshakes
/// use the current one.
pub(crate) type SharedTls = Arc<RwLock<Arc<rustls::ServerConfig>>>;

/// The connections of one listener, by id (ids grow, so the smallest
/// handshaking id is the oldest handshake).
#[derive(Default)]
struct Table {
    next: u64,
    handshaking: BTreeMap<u64, oneshot::Sender<()>>,
    open: HashMap<u64, Open>,
}

struct Open {
    /// When bytes last arrived, ms since the registry's epoch.
    last_read: Arc<AtomicU64>,
    close: oneshot::Sender<()>,
}

/// The table behind a lock, and the clock its times count from.
struct Registry {
    table: Mutex<Table>,
    epoch: Instant,
    limits: ListenerLimits,
    what: &'static str,
}

impl Registry {
    fn lock(&self) -> MutexGuard<'_, Table> {
        self.table
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    fn now_ms(&self) -> u64 {
        self.epoch.elapsed().as_millis() as u64
    }

    /// A new connection in its handshake, and what tells it to close; the
    /// oldest handshake closes if there are too many.
    fn begin(&self) -> (u64, oneshot::Receiver<()>) {
        let (tx, rx) = oneshot::channel();
        let mut table = self.lock();
        while table.handshaking.len() >= self.limits.max_handshakes {
            let Some((_, oldest)) = table.handshaking.pop_first() else {
                break;
            };
            let _ = oldest.send(());
        }
        let id = table.next;
        table.next += 1;
        table.handshaking.insert(id, tx);
        (id, rx)
    }

    /// Connection `id` finished its handshake; the connection silent the
    /// longest closes if too many are open. `None` if `id` was closed
    /// meanwhile.
    fn open(&self, id: u64) -> Option<(Arc<AtomicU64>, oneshot::Receiver<()>)> {
        let mut table = self.lock();
        table.handshaking.remove(&id)?;
        while table.open.len() >= self.limits.max_connections {
            let quietest = table
                .open
                .iter()
                .min_by_key(|(_, open)| open.last_read.load(Ordering::Relaxed))
                .map(|(&id, _)| id);
            let Some(quietest) = quietest else { break };
            if let Some(open) = table.open.remove(&quietest) {
                let _ = open.close.send(());
            }
        }
        let (close, rx) = oneshot::channel();
        let last_read = Arc::new(AtomicU64::new(self.now_ms()));
        table.open.insert(
            id,
            Open {
                last_read: last_read.clone(),
                close,
            },
        );
        Some((last_read, rx))
    }

    fn end(&self, id: u64) {
        let mut table = self.lock();
        table.handshaking.remove(&id);
        table.open.remove(&id);
    }
}

/// The connections a guarded listener accepts, ready for HTTP (TLS done
/// when `tls` is set): a stream for tonic, or for the metrics endpoint.
pub(crate) fn incoming(
    listener: TcpListener,
    tls: Option<SharedTls>,
    limits: ListenerLimits,
    what: &'static str,
) -> ReceiverStream<io::Result<Connection>> {
    let registry = Arc::new(Registry {
        table: Mutex::default(),
        epoch: Instant::now(),
        limits,
        what,
    });
    let (tx, rx) = mpsc::channel(limits.max_handshakes.max(16));
    tokio::spawn(accept_loop(listener, tls, registry, tx));
    ReceiverStream::new(rx)
}

async fn accept_loop(
    listener: TcpListener,
    tls: Option<SharedTls>,
    registry: Arc<Registry>,
    tx: mpsc::Sender<io::Result<Connection>>,
) {
    let mut errors = (Instant::now(), 0u32);
    loop {
        let accepted = tokio::select! {
            () = tx.closed() => return,
            accepted = listener.accept() => accepted,
        };
        let (stream, peer) = match accepted {
            Ok(accepted) => accepted,
            Err(e) => {
                if errors.0.elapsed() > Duration::from_secs(60) {
                    errors = (Instant::now(), 0);
                }
                errors.1 += 1;
                if errors.1 <= LOGGED_ERRORS_PER_MINUTE {
                    tracing::warn!(
                        listener = registry.what,
                        error = %e,
                        "accept failed (out of file descriptors? see LimitNOFILE); retrying in {ACCEPT_BACKOFF:?}"
                    );
                }
                tokio::time::sleep(ACCEPT_BACKOFF).await;
                continue;
            }
        };
        let _ = stream.set_nodelay(true);
        let (id, close) = registry.begin();
        let acceptor = tls.as_deref().map(|tls| TlsAcceptor::from(current(tls)));
        let (registry, tx) = (registry.clone(), tx.clone());
        tokio::spawn(async move {
            let guard = EndOnDrop(registry.clone(), id);
            let limit = registry.limits.handshake();
            let shaken = tokio::select! {
                _ = close => Err("closed to make room for newer connections".to_string()),
                shaken = tokio::time::timeout(limit, handshake(stream, acceptor)) => match shaken {
                    Ok(Ok(io)) => Ok(io),
                    Ok(Err(e)) => Err(e.to_string()),
                    Err(_) => Err(format!("no handshake within {limit:?}")),
                },
            };
            let io = match shaken {
                Ok(io) => io,
                Err(reason) => {
                    tracing::debug!(listener = registry.what, %peer, %reason, "connection dropped");
                    return;
                }
            };
            let Some((last_read, close)) = registry.open(id) else {
                return;
            };
            let connection = Connection {
                io,
                peer,
                close: Some(close),
                silence: Box::pin(tokio::time::sleep(registry.limits.handshake())),
                last_read_at: Instant::now(),
                last_read,
                got_bytes: false,
                guard,
            };
            let _ = tx.send(Ok(connection)).await;
        });
    }
}

/// The TLS handshake, or in plaintext the wait for the first bytes.
async fn handshake(stream: TcpStream, tls: Option<TlsAcceptor>) -> io::Result<Io> {
    match tls {
        Some(acceptor) => Ok(Io::Tls(Box::new(acceptor.accept(stream).await?))),
        None => {
            if stream.peek(&mut [0u8; 1]).await? == 0 {
                return Err(io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    "closed before sending anything",
                ));
            }
            Ok(Io::Plain(stream))
        }
    }
}

/// Removes a connection from its registry when it ends, however it ends.
struct EndOnDrop(Arc<Registry>, u64);

impl Drop for EndOnDrop {
    fn drop(&mut self) {
        self.0.end(self.1);
    }
}

enum Io {
    Plain(TcpStream),
    Tls(Box<TlsStream<TcpStream>>),
}

impl Io {
    fn tcp(&self) -> &TcpStream {
        match self {
            Self::Plain(tcp) => tcp,
            Self::Tls(tls) => tls.get_ref().0,
        }
    }
}

/// An accepted connection past its handshake. Reads fail once it has been
/// closed to make room or has been silent too long, which ends it.
pub(crate) struct Connection {
    io: Io,
    peer: SocketAddr,
    /// Fires when the connection is closed to make room; `None` once it has.
    close: Option<oneshot::Receiver<()>>,
    silence: Pin<Box<Sleep>>,
    last_read_at: Instant,
    last_read: Arc<AtomicU64>,
    /// Until the first bytes arrive, silence is bounded by the handshake
    /// timeout, afterwards by the idle timeout.
    got_bytes: bool,
    guard: EndOnDrop,
}

impl Connection {
    /// The peer's address.
    pub(crate) fn peer(&self) -> SocketAddr {
        self.peer
    }

    fn registry(&self) -> &Registry {
        &self.guard.0
    }
}

impl AsyncRead for Connection {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = &mut *self;
        let closed = match &mut this.close {
            Some(close) => Pin::new(close).poll(cx).is_ready(),
            None => true,
        };
        if closed {
            this.close = None;
            return Poll::Ready(Err(io::Error::new(
                io::ErrorKind::ConnectionAborted,
                "closed to make room for newer connections",
            )));
        }
        let before = buf.filled().len();
        let read = match &mut this.io {
            Io::Plain(tcp) => Pin::new(tcp).poll_read(cx, buf),
            Io::Tls(tls) => Pin::new(tls.as_mut()).poll_read(cx, buf),
        };
        if read.is_ready() {
            if buf.filled().len() > before {
                this.got_bytes = true;
                this.last_read_at = Instant::now();
                let now = this.registry().now_ms();
                this.last_read.store(now, Ordering::Relaxed);
            }
            return read;
        }
        let limits = this.registry().limits;
        let allowed = if this.got_bytes {
            limits.idle()
        } else {
            limits.handshake()
        };
        loop {
            ready!(this.silence.as_mut().poll(cx));
            let deadline = this.last_read_at + allowed;
            if Instant::now() >= deadline {
                return Poll::Ready(Err(io::Error::new(
                    io::ErrorKind::TimedOut,
                    format!("nothing received for {allowed:?}"),
                )));
            }
            this.silence.as_mut().reset(deadline.into());
        }
    }
}

impl AsyncWrite for Connection {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        match &mut self.io {
            Io::Plain(tcp) => Pin::new(tcp).poll_write(cx, buf),
            Io::Tls(tls) => Pin::new(tls.as_mut()).poll_write(cx, buf),
        }
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match &mut self.io {
            Io::Plain(tcp) => Pin::new(tcp).poll_flush(cx),
            Io::Tls(tls) => Pin::new(tls.as_mut()).poll_flush(cx),
        }
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match &mut self.io {
            Io::Plain(tcp) => Pin::new(tcp).poll_shutdown(cx),
            Io::Tls(tls) => Pin::new(tls.as_mut()).poll_shutdown(cx),
        }
    }
}

impl Connected for Connection {
    type ConnectInfo = TcpConnectInfo;

    fn connect_info(&self) -> TcpConnectInfo {
        TcpConnectInfo {
            local_addr: self.io.tcp().local_addr().ok(),
            remote_addr: Some(self.peer),
        }
    }
}

/// Raises this process's soft limit on open files toward its hard limit so
/// that `needed` descriptors fit; warns when even the hard limit is short.
pub fn raise_open_files_limit(needed: u64) {
    use nix::sys::resource::{Resource, getrlimit, setrlimit};
    let Ok((soft, hard)) = getrlimit(Resource::RLIMIT_NOFILE) else {
        return;
    };
    let wanted = needed.saturating_add(256);
    if soft >= wanted {
        return;
    }
    let target = wanted.min(hard);
    if target > soft && setrlimit(Resource::RLIMIT_NOFILE, target, hard).is_ok() {
        tracing::debug!(from = soft, to = target, "raised the open-files limit");
    }
    if target < wanted {
        tracing::warn!(
            limit = target,
            wanted,
            "the open-files limit is below what the listeners' connection caps allow: raise it (LimitNOFILE) or lower [listener] max_connections"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn registry(max_connections: usize, max_handshakes: usize) -> Registry {
        Registry {
            table: Mutex::default(),
            epoch: Instant::now(),
            limits: ListenerLimits {
                max_connections,
                max_handshakes,
                ..Default::default()
            },
            what: "test",
        }
    }

    #[test]
    fn the_oldest_handshake_makes_room() {
        let registry = registry(10, 2);
        let (a, mut a_close) = registry.begin();
        let (b, mut b_close) = registry.begin();
        let (_c, mut c_close) = registry.begin();
        assert!(a_close.try_recv().is_ok(), "the oldest closes");
        assert!(b_close.try_recv().is_err() && c_close.try_recv().is_err());
        assert!(registry.open(a).is_none(), "a closed handshake cannot open");
        assert!(registry.open(b).is_some());
    }

    #[test]
    fn the_longest_silent_open_connection_makes_room() {
        let registry = registry(2, 10);
        let ids: Vec<_> = (0..3).map(|_| registry.begin().0).collect();
        let (quiet, mut quiet_close) = registry.open(ids[0]).unwrap();
        let (busy, mut busy_close) = registry.open(ids[1]).unwrap();
        quiet.store(1, Ordering::Relaxed);
        busy.store(5, Ordering::Relaxed);
        let (_, mut new_close) = registry.open(ids[2]).unwrap();
        assert!(quiet_close.try_recv().is_ok());
        assert!(busy_close.try_recv().is_err() && new_close.try_recv().is_err());
        registry.end(ids[1]);
        assert_eq!(registry.lock().open.len(), 1);
    }

    #[test]
    fn limits_are_checked() {
        assert!(ListenerLimits::default().validate().is_ok());
        let bad = ListenerLimits {
            max_handshakes: 0,
            ..Default::default()
        };
        assert!(bad.validate().unwrap_err().contains("max_handshakes"));
        let bad = ListenerLimits {
            handshake_timeout_s: f64::NAN,
            ..Default::default()
        };
        assert!(bad.validate().unwrap_err().contains("handshake_timeout_s"));
    }
}
