//! A client's side: channels over TLS (unless plaintext) that send the
//! client's bearer token with every call, and connection errors that say
//! what to fix.

use crate::security::{Security, SecurityError};
use crate::server::chain;
use std::time::Duration;
use tonic::Code;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_client::HealthClient;
use tweezer_proto::pb;
use tweezer_proto::pb::learner_client::LearnerClient;

/// How often every client pings the server, busy or idle.
const PING_INTERVAL: Duration = Duration::from_secs(10);
/// How long a client waits for the answer to a ping before it takes the
/// connection for dead.
const PING_TIMEOUT: Duration = Duration::from_secs(10);

/// A channel that sends the client's token with every call.
pub type AuthChannel = InterceptedService<Channel, Bearer>;

/// Adds `authorization: Bearer <token>` to each call (nothing for an
/// anonymous client). `Debug` hides it.
#[derive(Clone)]
pub struct Bearer(Option<MetadataValue<Ascii>>);

impl std::fmt::Debug for Bearer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Bearer(<secret>)")
    }
}

impl Interceptor for Bearer {
    fn call(
        &mut self,
        mut request: tonic::Request<()>,
    ) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(value) = &self.0 {
            request
                .metadata_mut()
                .insert("authorization", value.clone());
        }
        Ok(request)
    }
}

/// How a client connects: TLS settings and its token.
#[derive(Clone, Debug)]
pub struct ClientSecurity {
    tls: Option<ClientTlsConfig>,
    /// Whether a client certificate is presented.
    certificate: bool,
    bearer: Bearer,
    source: String,
}

/// A connection that could not be made.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    /// The address does not parse, or its scheme contradicts the settings.
    #[error("`{address}` {reason}")]
    Address {
        /// As given.
        address: String,
        /// What is wrong.
        reason: String,
    },
    /// Nothing answered as expected there.
    #[error("cannot reach {url}: {cause}{hint}")]
    Unreachable {
        /// The URL tried.
        url: String,
        /// The transport's error and its causes.
        cause: String,
        /// What to check, if the cause suggests it.
        hint: String,
    },
}

impl ClientSecurity {
    /// The client settings of `security`: the CA (and the certificate to
    /// present, if set) parsed, and the token read.
    pub fn load(security: &Security) -> Result<Self, SecurityError> {
        let token = security.token()?;
        let value = MetadataValue::try_from(format!("Bearer {}", token.secret()))
            .expect("a parsed token is printable ASCII");
        Self::with_bearer(security, Bearer(Some(value)))
    }

    /// The client settings of `security` without a token: for health
    /// checks (open to all), as a probe makes them.
    pub fn anonymous(security: &Security) -> Result<Self, SecurityError> {
        Self::with_bearer(security, Bearer(None))
    }

    fn with_bearer(security: &Security, bearer: Bearer) -> Result<Self, SecurityError> {
        let pem = security.client_pem()?;
        let certificate = pem.as_ref().is_some_and(|p| p.identity.is_some());
        let tls = pem.map(|pem| {
            let mut tls = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(
                pem.ca.expect("a client's PEM has a CA"),
            ));
            if let Some((cert, key)) = pem.identity {
                tls = tls.identity(Identity::from_pem(cert, key));
            }
            tls
        });
        if tls.is_none() {
            tracing::warn!(
                security = %security.source,
                "TLS is off (plaintext = true): the token crosses the network in the clear"
            );
        }
        Ok(Self {
            tls,
            certificate,
            bearer,
            source: security.source.clone(),
        })
    }

    /// Whether TLS is off.
    pub fn plaintext(&self) -> bool {
        self.tls.is_none()
    }

    /// `address` (`host:port` or a URL) as a URL with the scheme these
    /// settings use.
    pub fn url(&self, address: &str) -> Result<String, ConnectError> {
        let scheme = if self.plaintext() { "http" } else { "https" };
        match address.split_once("://") {
            None => Ok(format!("{scheme}://{address}")),
            Some((given, _)) if given == scheme => Ok(address.to_string()),
            Some((given, rest)) => Err(ConnectError::Address {
                address: address.into(),
                reason: format!(
                    "is {given}:// but {} says {}: write {scheme}://{rest}, or just {rest}",
                    self.source,
                    if self.plaintext() {
                        "plaintext = true"
                    } else {
                        "TLS (plaintext is not set)"
                    }
                ),
            }),
        }
    }

    /// An endpoint for `address` with these TLS settings, pinging the
    /// server every [`PING_INTERVAL`]: a connection whose peer went
    /// away without a word (a partition, a dead relay) fails within
    /// [`PING_INTERVAL`] + [`PING_TIMEOUT`], and so do the calls
    /// waiting on it, instead of waiting for ever.
    pub fn endpoint(&self, address: &str) -> Result<Endpoint, ConnectError> {
        let url = self.url(address)?;
        let bad = |e: &dyn std::error::Error| ConnectError::Address {
            address: address.into(),
            reason: format!("is not an address: {e}"),
        };
        let mut endpoint = Endpoint::from_shared(url)
            .map_err(|e| bad(&e))?
            .http2_keep_alive_interval(PING_INTERVAL)
            .keep_alive_timeout(PING_TIMEOUT)
            .keep_alive_while_idle(true);
        if let Some(tls) = &self.tls {
            endpoint = endpoint.tls_config(tls.clone()).map_err(|e| bad(&e))?;
        }
        Ok(endpoint)
    }

    /// Connects to `address`, giving up after `timeout`, and proves the
    /// connection carries calls with a health check (which needs no token):
    /// a service that wants a client certificate, or TLS from a plaintext
    /// client, hangs up only after the handshake.
    pub async fn connect(
        &self,
        address: &str,
        timeout: Duration,
    ) -> Result<AuthChannel, ConnectError> {
        let (channel, _) = self.checked(address, timeout, None).await?;
        Ok(self.authed(channel))
    }

    /// As [`Self::connect`], and each call on the channel must be answered
    /// within `timeout` too.
    pub async fn connect_bounded(
        &self,
        address: &str,
        timeout: Duration,
    ) -> Result<AuthChannel, ConnectError> {
        let (channel, _) = self.checked(address, timeout, Some(timeout)).await?;
        Ok(self.authed(channel))
    }

    /// The health of `service` (`""`: the whole server) at `address`, as
    /// `grpc.health.v1` reports it: `SERVING`, `NOT_SERVING`, or
    /// `SERVICE_UNKNOWN` for a service the server does not have.
    pub async fn health(
        &self,
        address: &str,
        service: &str,
        timeout: Duration,
    ) -> Result<String, ConnectError> {
        let (channel, url) = self.checked(address, timeout, None).await?;
        match health(channel, service).await {
            Ok(reply) => Ok(reply.status().as_str_name().to_string()),
            Err(status) if status.code() == Code::NotFound => Ok("SERVICE_UNKNOWN".into()),
            Err(status) => Err(self.hung_up(&url, &status)),
        }
    }

    /// A channel to `address` that has answered a health check (calls
    /// bounded by `call_timeout`, if given), and its URL.
    async fn checked(
        &self,
        address: &str,
        timeout: Duration,
        call_timeout: Option<Duration>,
    ) -> Result<(Channel, String), ConnectError> {
        let mut endpoint = self
            .endpoint(address)?
            .connect_timeout(timeout)
            .tcp_nodelay(true);
        if let Some(call_timeout) = call_timeout {
            endpoint = endpoint.timeout(call_timeout);
        }
        let url = endpoint.uri().to_string().trim_end_matches('/').to_string();
        let channel = endpoint
            .connect()
            .await
            .map_err(|e| self.unreachable(&url, &e))?;
        match health(channel.clone(), "").await {
            Err(status)
                if matches!(
                    status.code(),
                    Code::Unknown | Code::Unavailable | Code::Internal | Code::Cancelled
                ) =>
            {
                Err(self.hung_up(&url, &status))
            }
            _ => Ok((channel, url)),
        }
    }

    /// The service ended a connection that had been made.
    fn hung_up(&self, url: &str, status: &tonic::Status) -> ConnectError {
        let cause = chain(status);
        let hint = hint(&cause, self.plaintext()).or(if self.plaintext() {
            Some("this client's security file says plaintext = true: the service probably wants TLS")
        } else if !self.certificate {
            Some(
                "the service hung up after the TLS handshake: it probably requires a client certificate (set `cert` and `key` in this client's security file)",
            )
        } else {
            None
        });
        ConnectError::Unreachable {
            url: url.into(),
            hint: hint.map(|h| format!("\n  {h}")).unwrap_or_default(),
            cause,
        }
    }

    /// `channel` with the token added to every call.
    pub fn authed(&self, channel: Channel) -> AuthChannel {
        InterceptedService::new(channel, self.bearer.clone())
    }

    fn unreachable(&self, url: &str, error: &tonic::transport::Error) -> ConnectError {
        let cause = chain(error);
        ConnectError::Unreachable {
            url: url.into(),
            hint: hint(&cause, self.plaintext())
                .map(|h| format!("\n  {h}"))
                .unwrap_or_default(),
            cause,
        }
    }
}

/// What to check, when a transport error's text suggests it.
pub fn hint(cause: &str, plaintext: bool) -> Option<&'static str> {
    let has = |s: &str| cause.to_ascii_lowercase().contains(&s.to_ascii_lowercase());
    if has("CertificateRequired") || has("certificate required") {
        Some(
            "the service requires a client certificate: set `cert` and `key` in this client's security file",
        )
    } else if has("UnknownIssuer") || has("NotValidForName") || has("certificate") {
        Some(
            "the service's certificate does not check out against this client's `ca` (another CA, or not issued for this host name)",
        )
    } else if has("InvalidContentType") || has("corrupt message") {
        Some(
            "the service does not speak TLS: its security file may say plaintext = true, and this client's does not",
        )
    } else if plaintext
        && (has("connection closed") || has("h2 protocol") || has("connection reset"))
    {
        Some("this client's security file says plaintext = true: the service probably wants TLS")
    } else if has("refused") || has("timed out") || has("dns") {
        Some(
            "is the service running and listening there? (check the address, and the flag, environment variable or config field it came from)",
        )
    } else {
        None
    }
}

/// One `grpc.health.v1` check of `service` over `channel`.
async fn health(
    channel: Channel,
    service: &str,
) -> Result<tonic_health::pb::HealthCheckResponse, tonic::Status> {
    HealthClient::new(channel)
        .check(HealthCheckRequest {
            service: service.into(),
        })
        .await
        .map(tonic::Response::into_inner)
}

/// The status of the learner `client` talks to.
pub async fn learner_status(
    client: &mut LearnerClient<AuthChannel>,
) -> Result<pb::LearnerStatus, tonic::Status> {
    Ok(client
        .get_status(pb::LearnerStatusRequest {})
        .await?
        .into_inner())
}
