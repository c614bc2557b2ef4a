//! The layer in front of every service: checks the bearer token against the
//! role the method needs (see [`crate::access`]), answers UNAUTHENTICATED
//! or PERMISSION_DENIED itself, and logs every state-changing call with the
//! name of the token that made it. Tokens never reach a log.

use crate::access::{Access, access};
use crate::server::{SharedTokens, current};
use crate::tokens::{Role, TokenEntry, Tokens};
use http::{Request, Response};
use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use tonic::Status;
use tonic::body::Body;
use tower::{Layer, Service};

/// Who made a call, in the request's extensions for the services.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Caller {
    /// The token's name in the tokens file.
    pub name: String,
    /// The token's role.
    pub role: Role,
}

/// Adds [`Authorize`] to a server.
#[derive(Clone)]
pub struct AuthLayer {
    tokens: SharedTokens,
}

impl AuthLayer {
    /// Accepts the tokens `tokens` holds at each call.
    pub(crate) fn new(tokens: SharedTokens) -> Self {
        Self { tokens }
    }
}

/// Why an `authorization` header is refused.
pub(crate) enum Refusal {
    /// There is none.
    Missing,
    /// It is not `Bearer <token>`.
    NotBearer,
    /// The token is not listed.
    Unknown,
}

/// The listed token an `authorization` header presents.
pub(crate) fn presented<'t>(
    tokens: &'t Tokens,
    header: Option<&http::HeaderValue>,
) -> Result<&'t TokenEntry, Refusal> {
    let header = header.ok_or(Refusal::Missing)?;
    let presented = header
        .to_str()
        .ok()
        .and_then(|h| h.split_once(' '))
        .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
        .map(|(_, token)| token.trim())
        .ok_or(Refusal::NotBearer)?;
    tokens.verify(presented).ok_or(Refusal::Unknown)
}

impl<S> Layer<S> for AuthLayer {
    type Service = Authorize<S>;

    fn layer(&self, inner: S) -> Self::Service {
        Authorize {
            inner,
            tokens: self.tokens.clone(),
        }
    }
}

/// A service behind token checks.
#[derive(Clone)]
pub struct Authorize<S> {
    inner: S,
    tokens: SharedTokens,
}

impl<S> Authorize<S> {
    /// The caller of `request`, or the status refusing it.
    fn check<B>(&self, request: &Request<B>) -> Result<Option<Caller>, Status> {
        let path = request.uri().path();
        let needed = match access(path) {
            Access::Open => return Ok(None),
            Access::Needs(role) => role,
        };
        let refuse = |status: Status| {
            tracing::warn!(method = path, code = ?status.code(), reason = status.message(), "call refused");
            Err(status)
        };
        let header = request.headers().get(http::header::AUTHORIZATION);
        let tokens = current(&self.tokens);
        let entry = match presented(&tokens, header) {
            Ok(entry) => entry,
            Err(Refusal::Missing) => {
                return refuse(Status::unauthenticated(format!(
                    "{path} needs a token with the `{needed}` role: send `authorization: Bearer <token>`"
                )));
            }
            Err(Refusal::NotBearer) => {
                return refuse(Status::unauthenticated(
                    "the authorization header is not `Bearer <token>`",
                ));
            }
            Err(Refusal::Unknown) => {
                return refuse(Status::unauthenticated(
                    "unknown token: this service's tokens file does not list it",
                ));
            }
        };
        if !entry.role.grants(needed) {
            return refuse(Status::permission_denied(format!(
                "the token `{}` has the `{}` role; {path} needs `{needed}`",
                entry.name, entry.role
            )));
        }
        if needed == Role::Control {
            tracing::info!(method = path, caller = %entry.name, "control call");
        } else {
            tracing::debug!(method = path, caller = %entry.name, "call");
        }
        Ok(Some(Caller {
            name: entry.name.clone(),
            role: entry.role,
        }))
    }
}

impl<S, B> Service<Request<B>> for Authorize<S>
where
    S: Service<Request<B>, Response = Response<Body>>,
    S::Future: Send + 'static,
{
    type Response = Response<Body>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Response<Body>, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut request: Request<B>) -> Self::Future {
        match self.check(&request) {
            Ok(caller) => {
                if let Some(caller) = caller {
                    request.extensions_mut().insert(caller);
                }
                Box::pin(self.inner.call(request))
            }
            Err(status) => {
                let response = status.into_http();
                Box::pin(async move { Ok(response) })
            }
        }
    }
}
