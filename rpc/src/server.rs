//! A process's gRPC listener: its service plus `grpc.health.v1` and server
//! reflection, behind TLS (unless the security file says plaintext) and
//! token checks, with a span per request.

use crate::authorize::{AuthLayer, LiveTokens, SharedTokens};
use crate::guarded_listener::{
    self, KEEPALIVE_INTERVAL, KEEPALIVE_TIMEOUT, ListenerLimits, PeerInfo, SharedTls,
};
use crate::security::{Pem, Security, SecurityError};
use anyhow::Context;
use http::Request;
use std::convert::Infallible;
use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};
use tokio::net::TcpListener;
use tonic::body::Body;
use tonic::server::NamedService;
use tonic::service::Routes;
use tonic::transport::Server;
use tower::Service;

/// Most streams a client may have open at once on one connection: an
/// actor holds one, a CLI or a snapshot follower a few.
pub const MAX_CONCURRENT_STREAMS: u32 = 32;
/// Streams the server may reset for a client's protocol errors on one
/// connection before it closes it with GOAWAY (ENHANCE_YOUR_CALM). tonic
/// passes none unless told, which switches h2's own limit off: one
/// connection could then make the server reset streams without end
/// ("MadeYouReset", CVE-2025-8671). Well-behaved clients cause none.
pub const MAX_LOCAL_ERROR_RESETS: usize = 128;
/// Streams a client may reset before the server has accepted them
/// ("Rapid Reset", CVE-2023-44487): h2's default, set here on purpose.
pub const MAX_PENDING_ACCEPT_RESETS: usize = 20;
/// Largest header list a client may send, bytes.
pub const MAX_HEADER_LIST_BYTES: u32 = 16 << 10;
/// Largest frame a client may send: HTTP/2's minimum, 16 KiB.
pub const MAX_FRAME_BYTES: u32 = 16 << 10;
/// How far a client may send ahead of what the service has read, per
/// stream and per connection: the memory one connection's unread
/// requests can hold.
pub const RECEIVE_WINDOW_BYTES: u32 = 1 << 20;

/// Puts `value` behind a reloadable lock, for the next reader.
fn replace<T: ?Sized>(lock: &RwLock<Arc<T>>, value: Arc<T>) {
    *lock
        .write()
        .unwrap_or_else(|poisoned| poisoned.into_inner()) = value;
}

/// The current value behind a reloadable lock.
pub(crate) fn current<T: ?Sized>(lock: &RwLock<Arc<T>>) -> Arc<T> {
    lock.read()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
        .clone()
}

/// How a service's listeners are secured and limited, loaded and checked
/// before they bind. Clones share one state, which SIGHUP reloads: the
/// tokens file, and the certificate, key and CA files the security file
/// names (the security file itself, with `plaintext` and `[listener]`, is
/// read once).
#[derive(Clone)]
pub struct ServerSecurity {
    security: Arc<Security>,
    /// TLS for gRPC (ALPN h2); `None` in plaintext.
    grpc_tls: Option<SharedTls>,
    /// The same certificate for the metrics endpoint (ALPN http/1.1).
    pub(crate) metrics_tls: Option<SharedTls>,
    pub(crate) tokens: SharedTokens,
    pub(crate) limits: ListenerLimits,
    watching_sighup: Arc<AtomicBool>,
}

/// A gRPC service as tonic generates it, which [`ServerSecurity::serve`]
/// and [`crate::Listeners::serve`] mount beside health and reflection.
pub trait GrpcService:
    Service<
        Request<Body>,
        Error = Infallible,
        Response: axum::response::IntoResponse,
        Future: Send + 'static,
    > + NamedService
    + Clone
    + Send
    + Sync
    + 'static
{
}

impl<S> GrpcService for S where
    S: Service<
            Request<Body>,
            Error = Infallible,
            Response: axum::response::IntoResponse,
            Future: Send + 'static,
        > + NamedService
        + Clone
        + Send
        + Sync
        + 'static
{
}

impl ServerSecurity {
    /// The listener settings of `security`: its certificate and key (and CA,
    /// for client certificates) parsed, its tokens read, its `[listener]`
    /// limits checked. Plaintext is allowed only as the file says, and
    /// logged as a warning.
    pub fn load(security: &Security) -> Result<Self, SecurityError> {
        let limits = security.file().listener;
        limits.validate().map_err(|reason| SecurityError::Field {
            file: security.source.clone(),
            field: "listener",
            reason,
        })?;
        // Two listeners (gRPC and metrics) at most per process.
        guarded_listener::raise_open_files_limit(limits.descriptors(2));
        let tokens = security.tokens()?;
        let (grpc_tls, metrics_tls) = match tls_configs(security)? {
            None => {
                tracing::warn!(
                    security = %security.source,
                    "TLS is off (plaintext = true): tokens and data cross the network in the clear"
                );
                (None, None)
            }
            Some((grpc, metrics)) => (
                Some(Arc::new(RwLock::new(grpc))),
                Some(Arc::new(RwLock::new(metrics))),
            ),
        };
        tracing::info!(
            tls = grpc_tls.is_some(),
            client_certificates = security.file().require_client_cert,
            tokens = tokens.len(),
            "listener security"
        );
        Ok(Self {
            security: Arc::new(security.clone()),
            grpc_tls,
            metrics_tls,
            tokens: LiveTokens::new(tokens),
            limits,
            watching_sighup: Arc::default(),
        })
    }

    /// Reads the tokens file and the certificates again and, if all of them
    /// load, uses them for new calls and handshakes; otherwise keeps the
    /// current ones and says why.
    pub fn reload(&self) -> Result<(), SecurityError> {
        let tokens = self.security.tokens()?;
        let configs = tls_configs(&self.security)?;
        let count = tokens.len();
        self.tokens.replace(tokens);
        if let (Some((grpc, metrics)), Some(grpc_tls), Some(metrics_tls)) =
            (configs, &self.grpc_tls, &self.metrics_tls)
        {
            replace(grpc_tls, grpc);
            replace(metrics_tls, metrics);
        }
        tracing::info!(tokens = count, "reloaded tokens and certificates");
        Ok(())
    }

    /// Reloads on every SIGHUP from now on (once per process however often
    /// it is asked).
    pub(crate) fn reload_on_sighup(&self) {
        if self.watching_sighup.swap(true, Ordering::SeqCst) {
            return;
        }
        use tokio::signal::unix::{SignalKind, signal};
        let mut hangups = match signal(SignalKind::hangup()) {
            Ok(hangups) => hangups,
            Err(e) => {
                tracing::warn!(error = %e, "cannot watch SIGHUP: tokens and certificates reload only on restart");
                return;
            }
        };
        let this = self.clone();
        let early = tweezer_process::early_hangup_came();
        tokio::spawn(async move {
            if early {
                tracing::info!("a SIGHUP came during start-up: reloading now");
                if let Err(e) = this.reload() {
                    tracing::error!(error = %e, "SIGHUP: reload failed; the previous tokens and certificates stay in use");
                }
            }
            while hangups.recv().await.is_some() {
                if let Err(e) = this.reload() {
                    tracing::error!(error = %e, "SIGHUP: reload failed; the previous tokens and certificates stay in use");
                }
            }
        });
    }

    /// The listener limits.
    pub fn limits(&self) -> ListenerLimits {
        self.limits
    }

    /// Serves `service`, health and reflection on `listener` until
    /// `shutdown` completes, then lets calls in flight finish.
    pub async fn serve<S>(
        self,
        listener: TcpListener,
        service: S,
        shutdown: impl Future<Output = ()> + Send,
    ) -> anyhow::Result<()>
    where
        S: GrpcService,
    {
        self.reload_on_sighup();
        let (health, health_service) = tonic_health::server::health_reporter();
        health
            .set_service_status(S::NAME, tonic_health::ServingStatus::Serving)
            .await;
        let reflection = tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(tweezer_proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
            .build_v1()
            .context("gRPC reflection")?;
        let routes = Routes::new(service)
            .add_service(health_service)
            .add_service(reflection);
        let incoming =
            guarded_listener::incoming(listener, self.grpc_tls.clone(), self.limits, "gRPC");
        Server::builder()
            .http2_keepalive_interval(Some(KEEPALIVE_INTERVAL))
            .http2_keepalive_timeout(Some(KEEPALIVE_TIMEOUT))
            .max_concurrent_streams(MAX_CONCURRENT_STREAMS)
            .http2_max_local_error_reset_streams(Some(MAX_LOCAL_ERROR_RESETS))
            .http2_max_pending_accept_reset_streams(Some(MAX_PENDING_ACCEPT_RESETS))
            .http2_max_header_list_size(MAX_HEADER_LIST_BYTES)
            .max_frame_size(MAX_FRAME_BYTES)
            .initial_stream_window_size(RECEIVE_WINDOW_BYTES)
            .initial_connection_window_size(RECEIVE_WINDOW_BYTES)
            .trace_fn(request_span)
            .layer(AuthLayer::new(self.tokens.clone()))
            .add_routes(routes)
            .serve_with_incoming_shutdown(incoming, shutdown)
            .await
            .context("gRPC server failed")
    }
}

/// TLS server configs for gRPC and for the metrics endpoint.
type TlsPair = (Arc<rustls::ServerConfig>, Arc<rustls::ServerConfig>);

/// The TLS server configs (gRPC, metrics) of `security`'s PEM files, or
/// `None` in plaintext.
fn tls_configs(security: &Security) -> Result<Option<TlsPair>, SecurityError> {
    let Some(pem) = security.server_pem()? else {
        return Ok(None);
    };
    // A certificate from another CA would lock out every client that
    // trusts the deployment's: refused at start and on reload alike.
    if let (Some(ca), Some((cert, _))) = (security.ca_pem()?, &pem.identity) {
        crate::certs::check_issued_by(cert, &ca).map_err(|reason| SecurityError::Field {
            file: security.source.clone(),
            field: "cert",
            reason,
        })?;
    }
    let config = |alpn: &[u8]| {
        server_tls(&pem, alpn)
            .map(Arc::new)
            .map_err(|reason| SecurityError::Field {
                file: security.source.clone(),
                field: "cert",
                reason,
            })
    };
    Ok(Some((config(b"h2")?, config(b"http/1.1")?)))
}

/// A rustls server config with `pem`'s certificate (and client CA), for
/// the application protocol `alpn`.
fn server_tls(pem: &Pem, alpn: &[u8]) -> Result<rustls::ServerConfig, String> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let (cert, key) = pem
        .identity
        .as_ref()
        .expect("a server's PEM has an identity");
    let certs = CertificateDer::pem_slice_iter(cert)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("the certificate does not load: {e}"))?;
    let key =
        PrivateKeyDer::from_pem_slice(key).map_err(|e| format!("the key does not load: {e}"))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ServerConfig::builder_with_provider(provider.clone())
        .with_safe_default_protocol_versions()
        .map_err(|e| e.to_string())?;
    let builder = match &pem.ca {
        None => builder.with_no_client_auth(),
        Some(ca) => {
            let mut roots = rustls::RootCertStore::empty();
            for cert in CertificateDer::pem_slice_iter(ca) {
                let cert = cert.map_err(|e| format!("the CA does not load: {e}"))?;
                roots
                    .add(cert)
                    .map_err(|e| format!("the CA does not load: {e}"))?;
            }
            let verifier = rustls::server::WebPkiClientVerifier::builder_with_provider(
                Arc::new(roots),
                provider,
            )
            .build()
            .map_err(|e| e.to_string())?;
            builder.with_client_cert_verifier(verifier)
        }
    };
    let mut config = builder
        .with_single_cert(certs, key)
        .map_err(|e| format!("the certificate and key do not load: {e}"))?;
    config.alpn_protocols = vec![alpn.to_vec()];
    Ok(config)
}

/// The span every request runs in: its method and the peer's address.
fn request_span(request: &http::Request<()>) -> tracing::Span {
    let peer = request
        .extensions()
        .get::<PeerInfo>()
        .and_then(|info| info.tcp.remote_addr());
    tracing::info_span!(
        "rpc",
        method = request.uri().path(),
        peer = peer.map(tracing::field::display)
    )
}

/// An error and its causes, one after another.
pub(crate) fn chain(error: &(dyn std::error::Error + 'static)) -> String {
    let mut text = error.to_string();
    let mut source = error.source();
    while let Some(cause) = source {
        let cause_text = cause.to_string();
        if !text.contains(&cause_text) {
            text.push_str(": ");
            text.push_str(&cause_text);
        }
        source = cause.source();
    }
    text
}
