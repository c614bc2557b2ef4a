//! Every listener's front door. Accepted TCP connections get a bounded TLS
//! handshake (in plaintext: a bound on the first bytes), an idle timeout,
//! and caps on how many may be handshaking and how many may be open. When a
//! cap is reached, the connection that matters least makes room:
//! - among handshakes, the oldest that has not sent a byte, else the
//!   oldest: a flood of silent connects, however fast, never displaces a
//!   client that has sent its ClientHello (an operator's EmergencyStop);
//! - among open connections, the one silent the longest that has made no
//!   authenticated call. Authenticated connections are never displaced by
//!   newcomers: when they alone fill the cap, the newcomer is closed.
//!
//! So silent or slow peers can only displace one another, and accept
//! errors (descriptors exhausted) back off instead of spinning.

use crate::server::current;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::io;
use std::mem::MaybeUninit;
use std::net::{IpAddr, SocketAddr};
use std::os::fd::{AsFd, OwnedFd};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
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
            // A silent connect costs a task and two descriptors; more room
            // gives a client longer to send its ClientHello under a flood
            // from its own address (10 ms at 24,000 connects/s).
            max_handshakes: 256,
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
    /// connections at most (a handshaking one holds two: see `Handshake`).
    pub fn descriptors(&self, listeners: usize) -> u64 {
        ((self.max_connections + 2 * self.max_handshakes) * listeners) as u64
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
    handshaking: BTreeMap<u64, Handshake>,
    open: HashMap<u64, Open>,
}

struct Handshake {
    /// The peer's address: a flood from one source makes room among its
    /// own connections.
    source: IpAddr,
    /// Set once the peer is known to have sent its first bytes (a
    /// ClientHello).
    spoke: Arc<AtomicBool>,
    /// The socket, to look for those bytes when room must be made: they
    /// may have arrived before the connection's task has run.
    socket: Option<OwnedFd>,
    close: oneshot::Sender<()>,
}

impl Handshake {
    /// Whether the peer has sent anything yet.
    fn spoke(&self) -> bool {
        if self.spoke.load(Ordering::Relaxed) {
            return true;
        }
        // Accepted sockets do not block: an empty one answers WouldBlock.
        let waiting = self.socket.as_ref().is_some_and(|socket| {
            matches!(
                socket2::SockRef::from(socket).peek(&mut [MaybeUninit::uninit()]),
                Ok(1..)
            )
        });
        if waiting {
            self.spoke.store(true, Ordering::Relaxed);
        }
        waiting
    }
}

impl Table {
    /// The handshake to close when there are too many: among those of the
    /// source with the most, the oldest silent one, or its oldest.
    fn least_needed_handshake(&self) -> Option<u64> {
        let mut counts: HashMap<IpAddr, usize> = HashMap::new();
        for handshake in self.handshaking.values() {
            *counts.entry(handshake.source).or_default() += 1;
        }
        let (&heaviest, _) = counts.iter().max_by_key(|(_, count)| **count)?;
        let mut theirs = self
            .handshaking
            .iter()
            .filter(|(_, h)| h.source == heaviest);
        let oldest = theirs.clone().next().map(|(&id, _)| id);
        theirs
            .find(|(_, h)| !h.spoke())
            .map(|(&id, _)| id)
            .or(oldest)
    }
}

struct Open {
    /// When bytes last arrived, ms since the registry's epoch.
    last_read: Arc<AtomicU64>,
    /// Set by the first call that presents a valid token.
    vouched: Arc<AtomicBool>,
    close: oneshot::Sender<()>,
}

/// An open connection's handles on its entry in the table.
struct Opened {
    last_read: Arc<AtomicU64>,
    vouched: Arc<AtomicBool>,
    close: oneshot::Receiver<()>,
}

/// What tonic hands each request about its connection: the addresses, and
/// a way to give the connection the standing of an authenticated one.
#[derive(Clone, Debug)]
pub(crate) struct PeerInfo {
    pub(crate) tcp: TcpConnectInfo,
    vouched: Arc<AtomicBool>,
}

impl PeerInfo {
    /// A call on this connection presented a valid token: newcomers no
    /// longer displace it.
    pub(crate) fn vouch(&self) {
        self.vouched.store(true, Ordering::Relaxed);
    }
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

    /// A new connection from `source` in its handshake, what tells it to
    /// close, and the flag to set when it speaks. If too many are
    /// handshaking, one of the source holding the most handshakes closes:
    /// its oldest silent one, or its oldest if all of them have spoken.
    fn begin(
        &self,
        source: IpAddr,
        socket: Option<OwnedFd>,
    ) -> (u64, oneshot::Receiver<()>, Arc<AtomicBool>) {
        let (close, rx) = oneshot::channel();
        let spoke = Arc::new(AtomicBool::new(false));
        let mut table = self.lock();
        while table.handshaking.len() >= self.limits.max_handshakes {
            let Some(id) = table.least_needed_handshake() else {
                break;
            };
            if let Some(handshake) = table.handshaking.remove(&id) {
                let _ = handshake.close.send(());
            }
        }
        let id = table.next;
        table.next += 1;
        let handshake = Handshake {
            source,
            spoke: spoke.clone(),
            socket,
            close,
        };
        table.handshaking.insert(id, handshake);
        (id, rx, spoke)
    }

    /// Connection `id` finished its handshake. If too many are open, the
    /// one silent the longest among those without an authenticated call
    /// closes; if every open one has made one, `id` itself is refused.
    /// `None` if `id` is refused or was closed meanwhile.
    fn open(&self, id: u64) -> Option<Opened> {
        let mut table = self.lock();
        table.handshaking.remove(&id)?;
        while table.open.len() >= self.limits.max_connections {
            let quietest = table
                .open
                .iter()
                .filter(|(_, open)| !open.vouched.load(Ordering::Relaxed))
                .min_by_key(|(_, open)| open.last_read.load(Ordering::Relaxed))
                .map(|(&id, _)| id);
            let Some(quietest) = quietest else {
                tracing::warn!(
                    listener = self.what,
                    max_connections = self.limits.max_connections,
                    "refused a connection: authenticated clients hold every connection ([listener] max_connections)"
                );
                return None;
            };
            if let Some(open) = table.open.remove(&quietest) {
                let _ = open.close.send(());
            }
        }
        let (close, rx) = oneshot::channel();
        let last_read = Arc::new(AtomicU64::new(self.now_ms()));
        let vouched = Arc::new(AtomicBool::new(false));
        table.open.insert(
            id,
            Open {
                last_read: last_read.clone(),
                vouched: vouched.clone(),
                close,
            },
        );
        Some(Opened {
            last_read,
            vouched,
            close: rx,
        })
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
        let socket = stream.as_fd().try_clone_to_owned().ok();
        let (id, close, spoke) = registry.begin(peer.ip(), socket);
        let acceptor = tls.as_deref().map(|tls| TlsAcceptor::from(current(tls)));
        let (registry, tx) = (registry.clone(), tx.clone());
        tokio::spawn(async move {
            let guard = EndOnDrop(registry.clone(), id);
            let limit = registry.limits.handshake();
            let shaken = tokio::select! {
                _ = close => Err("closed to make room for newer connections".to_string()),
                shaken = tokio::time::timeout(limit, handshake(stream, acceptor, &spoke)) => match shaken {
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
            let Some(Opened {
                last_read,
                vouched,
                close,
            }) = registry.open(id)
            else {
                return;
            };
            let connection = Connection {
                io,
                peer,
                vouched,
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

/// The wait for the first bytes (which sets `spoke`), then the TLS
/// handshake unless plaintext.
async fn handshake(
    stream: TcpStream,
    tls: Option<TlsAcceptor>,
    spoke: &AtomicBool,
) -> io::Result<Io> {
    if stream.peek(&mut [0u8; 1]).await? == 0 {
        return Err(io::Error::new(
            io::ErrorKind::UnexpectedEof,
            "closed before sending anything",
        ));
    }
    spoke.store(true, Ordering::Relaxed);
    match tls {
        Some(acceptor) => Ok(Io::Tls(Box::new(acceptor.accept(stream).await?))),
        None => Ok(Io::Plain(stream)),
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
    vouched: Arc<AtomicBool>,
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

    /// The connection's address and standing, for its requests.
    pub(crate) fn info(&self) -> PeerInfo {
        PeerInfo {
            tcp: TcpConnectInfo {
                local_addr: self.io.tcp().local_addr().ok(),
                remote_addr: Some(self.peer),
            },
            vouched: self.vouched.clone(),
        }
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
    type ConnectInfo = PeerInfo;

    fn connect_info(&self) -> PeerInfo {
        self.info()
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

    const HERE: IpAddr = IpAddr::V4(std::net::Ipv4Addr::LOCALHOST);

    #[test]
    fn a_flood_from_one_source_makes_room_among_its_own_handshakes() {
        let registry = registry(10, 3);
        let flood: IpAddr = [10, 0, 0, 9].into();
        let (_, mut operator_close, _) = registry.begin(HERE, None);
        let mut flooding: Vec<_> = (0..50).map(|_| registry.begin(flood, None).1).collect();
        assert!(
            operator_close.try_recv().is_err(),
            "the oldest, silent, but alone from its source"
        );
        let open = flooding
            .iter_mut()
            .map(|close| close.try_recv().is_err())
            .filter(|&open| open)
            .count();
        assert_eq!(open, 2, "the flood's newest two remain");
    }

    #[test]
    fn the_oldest_silent_handshake_makes_room() {
        let registry = registry(10, 2);
        let (a, mut a_close, a_spoke) = registry.begin(HERE, None);
        let (b, mut b_close, _) = registry.begin(HERE, None);
        a_spoke.store(true, Ordering::Relaxed);
        let (c, mut c_close, _) = registry.begin(HERE, None);
        assert!(b_close.try_recv().is_ok(), "the oldest silent one closes");
        assert!(a_close.try_recv().is_err() && c_close.try_recv().is_err());
        assert!(registry.open(b).is_none(), "a closed handshake cannot open");
        assert!(registry.open(a).is_some());
        let (_d, _, d_spoke) = registry.begin(HERE, None);
        d_spoke.store(true, Ordering::Relaxed);
        registry
            .lock()
            .handshaking
            .get(&c)
            .unwrap()
            .spoke
            .store(true, Ordering::Relaxed);
        let _e = registry.begin(HERE, None);
        assert!(c_close.try_recv().is_ok(), "all spoke: the oldest closes");
    }

    #[test]
    fn the_longest_silent_unauthenticated_connection_makes_room() {
        let registry = registry(2, 10);
        let ids: Vec<_> = (0..4).map(|_| registry.begin(HERE, None).0).collect();
        let mut quiet = registry.open(ids[0]).unwrap();
        let mut busy = registry.open(ids[1]).unwrap();
        quiet.last_read.store(1, Ordering::Relaxed);
        busy.last_read.store(5, Ordering::Relaxed);
        quiet.vouched.store(true, Ordering::Relaxed);
        let mut new = registry.open(ids[2]).unwrap();
        assert!(
            busy.close.try_recv().is_ok(),
            "the quieter one is authenticated"
        );
        assert!(quiet.close.try_recv().is_err() && new.close.try_recv().is_err());
        new.vouched.store(true, Ordering::Relaxed);
        assert!(
            registry.open(ids[3]).is_none(),
            "authenticated connections fill the cap: the newcomer is refused"
        );
        assert!(quiet.close.try_recv().is_err() && new.close.try_recv().is_err());
        registry.end(ids[0]);
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
