//! Actors' steps, from the gRPC edge into the replay: the service decodes a
//! batch, the session it belongs to is checked and deduplicated, and the
//! [`table::Table`] stores it as its rate limiter allows.

pub mod batch;
pub mod episodes;
pub mod limiter;
pub mod metrics;
pub mod service;
pub mod sessions;
pub mod status;
pub mod table;
