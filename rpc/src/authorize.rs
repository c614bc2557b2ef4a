//! The layer in front of every service: checks the bearer token against the
//! role the method needs (see [`crate::access`]), answers UNAUTHENTICATED
//! or PERMISSION_DENIED itself, and logs every state-changing call with the
//! name of the token that made it. Tokens never reach a log. A call's
//! streams stay bound to its token: once a reload revokes the token (or
//! takes the role away), the request stream fails and the response ends
//! with UNAUTHENTICATED, however long the call has been open.

use crate::access::{Access, access};
use crate::guarded_listener::PeerInfo;
use crate::tokens::{Role, TokenEntry, Tokens};
use http::{HeaderMap, Request, Response};
use hyper::body::{Bytes, Frame, SizeHint};
use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, RwLock};
use std::task::{Context, Poll, ready};
use tokio::sync::watch;
use tonic::Status;
use tonic::body::Body;
use tower::{Layer, Service};

/// The tokens a service accepts now. A reload replaces them and tells
/// every open call, which checks its token again.
pub(crate) struct LiveTokens {
    tokens: RwLock<Arc<Tokens>>,
    reloads: watch::Sender<()>,
}

/// The tokens of a process's listeners, shared with its reloads.
pub(crate) type SharedTokens = Arc<LiveTokens>;

impl LiveTokens {
    pub(crate) fn new(tokens: Tokens) -> SharedTokens {
        Arc::new(Self {
            tokens: RwLock::new(Arc::new(tokens)),
            reloads: watch::Sender::new(()),
        })
    }

    /// The tokens accepted now.
    pub(crate) fn current(&self) -> Arc<Tokens> {
        self.tokens
            .read()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .clone()
    }

    /// Accepts `tokens` from now on, open calls included.
    pub(crate) fn replace(&self, tokens: Tokens) {
        *self
            .tokens
            .write()
            .unwrap_or_else(|poisoned| poisoned.into_inner()) = Arc::new(tokens);
        self.reloads.send_replace(());
    }
}

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

/// A caller's token and the role its method needs: what every frame of
/// its streams is checked against after a reload.
#[derive(Clone)]
struct Grant {
    entry: TokenEntry,
    needed: Role,
    tokens: SharedTokens,
}

impl Grant {
    /// Whether the current tokens still grant the call.
    fn holds(&self) -> bool {
        self.tokens.current().grants(&self.entry, self.needed)
    }

    fn revoked(&self) -> Status {
        Status::unauthenticated(format!(
            "the token `{}` was revoked (or lost the `{}` role) while this call was open",
            self.entry.name, self.needed
        ))
    }
}

impl<S> Authorize<S> {
    /// The caller of `request` and what it was granted, or the status
    /// refusing it.
    fn check<B>(&self, request: &Request<B>) -> Result<Option<(Caller, Grant)>, Status> {
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
        let tokens = self.tokens.current();
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
        let caller = Caller {
            name: entry.name.clone(),
            role: entry.role,
        };
        let grant = Grant {
            entry: entry.clone(),
            needed,
            tokens: self.tokens.clone(),
        };
        Ok(Some((caller, grant)))
    }
}

impl<S> Service<Request<Body>> for Authorize<S>
where
    S: Service<Request<Body>, Response = Response<Body>>,
    S::Future: Send + 'static,
{
    type Response = Response<Body>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Response<Body>, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut request: Request<Body>) -> Self::Future {
        match self.check(&request) {
            Ok(None) => Box::pin(self.inner.call(request)),
            Ok(Some((caller, grant))) => {
                if let Some(peer) = request.extensions().get::<PeerInfo>() {
                    peer.vouch();
                }
                request.extensions_mut().insert(caller);
                let request_grant = grant.clone();
                let request =
                    request.map(|body| Body::new(Revocable::new(body, request_grant, End::Error)));
                let response = self.inner.call(request);
                Box::pin(async move {
                    let response = response.await?;
                    Ok(response.map(|body| Body::new(Revocable::new(body, grant, End::Trailers))))
                })
            }
            Err(status) => {
                let response = status.into_http();
                Box::pin(async move { Ok(response) })
            }
        }
    }
}

/// How a [`Revocable`] body ends once its grant is revoked.
#[derive(Clone, Copy)]
enum End {
    /// A request body: the service's next read fails.
    Error,
    /// A response body: trailers with UNAUTHENTICATED.
    Trailers,
}

/// The next reload, as a future that hands its receiver back.
type NextReload = Pin<Box<dyn Future<Output = Option<watch::Receiver<()>>> + Send>>;

fn next_reload(mut reloads: watch::Receiver<()>) -> NextReload {
    Box::pin(async move { reloads.changed().await.ok().map(|()| reloads) })
}

/// A call's body that ends as `end` says once a reload no longer grants
/// its token the call; frames pass through until then.
struct Revocable {
    inner: Body,
    grant: Grant,
    end: End,
    /// `None` once the body has ended (or the tokens can no longer change).
    reload: Option<NextReload>,
    ended: bool,
}

impl Revocable {
    fn new(inner: Body, grant: Grant, end: End) -> Self {
        let reload = Some(next_reload(grant.tokens.reloads.subscribe()));
        Self {
            inner,
            grant,
            end,
            reload,
            ended: false,
        }
    }

    /// Whether a reload since the last poll revoked the grant.
    fn revoked(&mut self, cx: &mut Context<'_>) -> bool {
        while let Some(reload) = self.reload.as_mut() {
            let Poll::Ready(next) = reload.as_mut().poll(cx) else {
                return false;
            };
            self.reload = next.map(next_reload);
            if !self.grant.holds() {
                return true;
            }
        }
        false
    }
}

impl hyper::body::Body for Revocable {
    type Data = Bytes;
    type Error = Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        let this = &mut *self;
        if this.ended {
            return Poll::Ready(None);
        }
        if this.revoked(cx) {
            this.ended = true;
            let status = this.grant.revoked();
            tracing::warn!(caller = %this.grant.entry.name, "ended a call whose token was revoked");
            return Poll::Ready(Some(match this.end {
                End::Error => Err(status),
                End::Trailers => {
                    let mut trailers = HeaderMap::new();
                    // The message is ASCII: token names are.
                    let _ = status.add_header(&mut trailers);
                    Ok(Frame::trailers(trailers))
                }
            }));
        }
        let frame = ready!(Pin::new(&mut this.inner).poll_frame(cx));
        if frame.is_none() {
            this.ended = true;
        }
        Poll::Ready(frame)
    }

    fn is_end_stream(&self) -> bool {
        self.ended || self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}
