//! `GET /metrics` on a listener of its own, secured as the gRPC listener
//! is: TLS with the same certificate (and client certificates when
//! required) unless plaintext, and a bearer token of any role (every role
//! may read). Prometheus scrapes it with `authorization` and `tls_config`.

use crate::authorize::{Refusal, presented};
use crate::prometheus::Prometheus;
use crate::server::ServerSecurity;
use crate::tokens::Tokens;
use http::{Method, Request, Response, StatusCode, header};
use http_body_util::Full;
use hyper::body::{Bytes, Incoming};
use hyper::server::conn::http1;
use hyper::service::service_fn;
use hyper_util::rt::TokioIo;
use std::convert::Infallible;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::TcpListener;
use tokio_rustls::TlsAcceptor;

/// Longest a scrape connection may stay open.
const CONNECTION_LIMIT: Duration = Duration::from_secs(30);

impl ServerSecurity {
    /// Serves `metrics` at `/metrics` on `listener` until `shutdown`.
    pub async fn serve_metrics(
        &self,
        listener: TcpListener,
        metrics: Arc<Prometheus>,
        shutdown: impl Future<Output = ()>,
    ) {
        let acceptor = self.metrics_tls.clone().map(TlsAcceptor::from);
        tokio::pin!(shutdown);
        loop {
            let stream = tokio::select! {
                () = &mut shutdown => return,
                accepted = listener.accept() => match accepted {
                    Ok((stream, _)) => stream,
                    Err(e) => {
                        tracing::debug!(error = %e, "metrics accept failed");
                        continue;
                    }
                },
            };
            let tokens = self.tokens.clone();
            let metrics = metrics.clone();
            let acceptor = acceptor.clone();
            tokio::spawn(async move {
                match acceptor {
                    Some(acceptor) => match acceptor.accept(stream).await {
                        Ok(tls) => connection(tls, tokens, metrics).await,
                        Err(e) => tracing::debug!(error = %e, "metrics TLS handshake failed"),
                    },
                    None => connection(stream, tokens, metrics).await,
                }
            });
        }
    }
}

/// Serves one connection's requests.
async fn connection<Io>(io: Io, tokens: Arc<Tokens>, metrics: Arc<Prometheus>)
where
    Io: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    let service = service_fn(move |request: Request<Incoming>| {
        let response = respond(&tokens, &metrics, &request);
        async move { Ok::<_, Infallible>(response) }
    });
    let served = http1::Builder::new().serve_connection(TokioIo::new(io), service);
    match tokio::time::timeout(CONNECTION_LIMIT, served).await {
        Ok(Err(e)) => tracing::debug!(error = %e, "metrics connection failed"),
        Err(_) => tracing::debug!("metrics connection closed after {CONNECTION_LIMIT:?}"),
        Ok(Ok(())) => {}
    }
}

fn respond<B>(
    tokens: &Tokens,
    metrics: &Prometheus,
    request: &Request<B>,
) -> Response<Full<Bytes>> {
    let reply = |status: StatusCode, body: String| {
        let mut response = Response::new(Full::new(Bytes::from(body)));
        *response.status_mut() = status;
        response
    };
    if request.uri().path() != "/metrics" {
        return reply(StatusCode::NOT_FOUND, "only /metrics is here\n".into());
    }
    if request.method() != Method::GET {
        return reply(StatusCode::METHOD_NOT_ALLOWED, "GET /metrics\n".into());
    }
    let refused = match presented(tokens, request.headers().get(header::AUTHORIZATION)) {
        Ok(_) => None,
        Err(Refusal::Missing) => Some("send `authorization: Bearer <token>` (any role)\n"),
        Err(Refusal::NotBearer) => Some("the authorization header is not `Bearer <token>`\n"),
        Err(Refusal::Unknown) => Some("unknown token\n"),
    };
    if let Some(reason) = refused {
        tracing::warn!(reason = reason.trim_end(), "metrics scrape refused");
        let mut response = reply(StatusCode::UNAUTHORIZED, reason.into());
        response.headers_mut().insert(
            header::WWW_AUTHENTICATE,
            header::HeaderValue::from_static("Bearer"),
        );
        return response;
    }
    let mut response = reply(StatusCode::OK, metrics.encode());
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        header::HeaderValue::from_static(
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        ),
    );
    response
}
