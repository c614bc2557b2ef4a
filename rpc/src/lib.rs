//! The gRPC edge every process shares. A security file says how a process
//! listens and connects ([`Security`]): TLS with the deployment's CA
//! (mutual TLS when a service requires client certificates), or plain TCP
//! when the file says so; bearer tokens with roles ([`Role`]) checked on
//! every call ([`access`] lists what each RPC needs). Services get health
//! checking, reflection and a span per request ([`ServerSecurity::serve`]);
//! clients get channels that send their token ([`ClientSecurity`]); each
//! process exposes its [`Prometheus`] metrics the same way, and every
//! service runs from bind to exit alike ([`Listeners`]).

pub mod access;
mod authorize;
pub mod certs;
mod client;
mod guarded_listener;
mod lifecycle;
mod loopback_credentials;
mod metrics_endpoint;
mod private_file;
pub mod prometheus;
mod security;
mod server;
mod tokens;

pub use authorize::Caller;
pub use client::{AuthChannel, Bearer, ClientSecurity, ConnectError, hint, learner_status};
pub use guarded_listener::{ListenerLimits, raise_open_files_limit};
pub use lifecycle::{Listeners, Stopping};
pub use loopback_credentials::LoopbackCredentials;
pub use private_file::{append_private, create_private};
pub use prometheus::{Histogram, MetricSample, Prometheus, latency_buckets};
pub use security::{Pem, SECURITY_ENV, Security, SecurityError, SecurityFile, TOKEN_ENV};
pub use server::{
    GrpcService, MAX_CONCURRENT_STREAMS, MAX_FRAME_BYTES, MAX_HEADER_LIST_BYTES,
    MAX_LOCAL_ERROR_RESETS, MAX_PENDING_ACCEPT_RESETS, RECEIVE_WINDOW_BYTES, ServerSecurity,
};
pub use tokens::{Role, Token, TokenEntry, TokenError, Tokens};
