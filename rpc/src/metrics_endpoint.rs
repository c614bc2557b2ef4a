//! `GET /metrics` on a listener of its own, secured as the gRPC listener
//! is: TLS with the same certificate (and client certificates when
//! required) unless plaintext, and a bearer token of any role (every role
//! may read), with the same connection limits. Prometheus scrapes it with
//! `authorization` and `tls_config`.

use crate::authorize::SharedTokens;
use crate::authorize::{Refusal, presented};
use crate::guarded_listener::{self, Connection};
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
use tokio::net::TcpListener;
use tokio_stream::StreamExt;

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
        self.reload_on_sighup();
        let mut incoming =
            guarded_listener::incoming(listener, self.metrics_tls.clone(), self.limits, "metrics");
        tokio::pin!(shutdown);
        loop {
            let connection = tokio::select! {
                () = &mut shutdown => return,
                accepted = incoming.next() => match accepted {
                    Some(Ok(connection)) => connection,
                    Some(Err(_)) => continue,
                    None => return,
                },
            };
            let tokens = self.tokens.clone();
            let metrics = metrics.clone();
            tokio::spawn(serve_connection(connection, tokens, metrics));
        }
    }
}

/// Serves one connection's requests.
async fn serve_connection(connection: Connection, tokens: SharedTokens, metrics: Arc<Prometheus>) {
    let peer = connection.peer();
    let info = connection.info();
    let service = service_fn(move |request: Request<Incoming>| {
        let response = respond(&tokens.current(), &metrics, &request);
        if response.status() == StatusCode::OK {
            info.vouch();
        }
        async move { Ok::<_, Infallible>(response) }
    });
    let served = http1::Builder::new().serve_connection(TokioIo::new(connection), service);
    match tokio::time::timeout(CONNECTION_LIMIT, served).await {
        Ok(Err(e)) => tracing::debug!(%peer, error = %e, "metrics connection failed"),
        Err(_) => tracing::debug!(%peer, "metrics connection closed after {CONNECTION_LIMIT:?}"),
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
    // OpenMetrics to a scraper that asks for it, the 0.0.4 text otherwise.
    let openmetrics = request
        .headers()
        .get(header::ACCEPT)
        .and_then(|accept| accept.to_str().ok())
        .is_some_and(|accept| accept.contains("application/openmetrics-text"));
    let (body, content_type) = if openmetrics {
        (
            metrics.encode(),
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )
    } else {
        (
            metrics.encode_text(),
            "text/plain; version=0.0.4; charset=utf-8",
        )
    };
    let mut response = reply(StatusCode::OK, body);
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        header::HeaderValue::from_static(content_type),
    );
    response
}
