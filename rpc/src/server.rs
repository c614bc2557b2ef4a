//! A process's gRPC listener: its service plus `grpc.health.v1` and server
//! reflection, behind TLS (unless the security file says plaintext) and
//! token checks, with a span per request.

use crate::authorize::AuthLayer;
use crate::security::{Pem, Security, SecurityError};
use crate::tokens::Tokens;
use anyhow::Context;
use http::Request;
use std::convert::Infallible;
use std::future::Future;
use std::sync::Arc;
use tokio::net::TcpListener;
use tokio_stream::wrappers::TcpListenerStream;
use tonic::body::Body;
use tonic::server::NamedService;
use tonic::service::Routes;
use tonic::transport::server::{ServerTlsConfig, TcpConnectInfo, TlsConnectInfo};
use tonic::transport::{Certificate, Identity, Server};
use tower::Service;

/// How a service's listener is secured, loaded and checked before it binds.
#[derive(Clone)]
pub struct ServerSecurity {
    tls: Option<ServerTlsConfig>,
    /// The same certificate for the metrics endpoint (HTTP/1.1).
    pub(crate) metrics_tls: Option<Arc<rustls::ServerConfig>>,
    pub(crate) tokens: Arc<Tokens>,
}

impl ServerSecurity {
    /// The listener settings of `security`: its certificate and key (and CA,
    /// for client certificates) parsed, its tokens read. Plaintext is
    /// allowed only as the file says, and logged as a warning.
    pub fn load(security: &Security) -> Result<Self, SecurityError> {
        let tokens = Arc::new(security.tokens()?);
        let pem = security.server_pem()?;
        let metrics_tls = pem
            .as_ref()
            .map(|pem| metrics_tls(pem).map(Arc::new))
            .transpose()
            .map_err(|reason| SecurityError::Field {
                file: security.source.clone(),
                field: "cert",
                reason,
            })?;
        let tls = match pem {
            None => {
                tracing::warn!(
                    security = %security.source,
                    "TLS is off (plaintext = true): tokens and data cross the network in the clear"
                );
                None
            }
            Some(pem) => {
                let (cert, key) = pem.identity.expect("a server's PEM has an identity");
                let mut tls = ServerTlsConfig::new().identity(Identity::from_pem(cert, key));
                if let Some(ca) = pem.ca {
                    tls = tls.client_ca_root(Certificate::from_pem(ca));
                }
                // Parse now, so a bad file is reported before anything starts.
                Server::builder()
                    .tls_config(tls.clone())
                    .map_err(|e| SecurityError::Field {
                        file: security.source.clone(),
                        field: "cert",
                        reason: format!("the certificate or key does not load: {}", chain(&e)),
                    })?;
                Some(tls)
            }
        };
        tracing::info!(
            tls = tls.is_some(),
            client_certificates = security.file().require_client_cert,
            tokens = tokens.len(),
            "listener security"
        );
        Ok(Self {
            tls,
            metrics_tls,
            tokens,
        })
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
        S: Service<Request<Body>, Error = Infallible>
            + NamedService
            + Clone
            + Send
            + Sync
            + 'static,
        S::Response: axum::response::IntoResponse,
        S::Future: Send + 'static,
    {
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
        let mut builder = Server::builder();
        if let Some(tls) = self.tls {
            builder = builder.tls_config(tls)?;
        }
        builder
            .trace_fn(request_span)
            .layer(AuthLayer::new(self.tokens))
            .add_routes(routes)
            .serve_with_incoming_shutdown(TcpListenerStream::new(listener), shutdown)
            .await
            .context("gRPC server failed")
    }
}

/// A rustls server config with `pem`'s certificate (and client CA), for
/// HTTP/1.1.
fn metrics_tls(pem: &Pem) -> Result<rustls::ServerConfig, String> {
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
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(config)
}

/// The span every request runs in: its method and the peer's address.
fn request_span(request: &http::Request<()>) -> tracing::Span {
    let extensions = request.extensions();
    let peer = extensions
        .get::<TlsConnectInfo<TcpConnectInfo>>()
        .and_then(|info| info.get_ref().remote_addr())
        .or_else(|| {
            extensions
                .get::<TcpConnectInfo>()
                .and_then(TcpConnectInfo::remote_addr)
        });
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
