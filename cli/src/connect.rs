//! Connecting to a service, with errors that say what to do about them.

use anyhow::anyhow;
use std::time::Duration;
use tonic::transport::{Channel, Endpoint};

/// How long a connection attempt and each call may take.
const TIMEOUT: Duration = Duration::from_secs(10);

/// A channel to `address` (`host:port` or a URL); `what` names the service
/// in errors, `flag` the option that sets its address.
pub async fn channel(address: &str, what: &str, flag: &str) -> anyhow::Result<Channel> {
    let url = if address.contains("://") {
        address.to_string()
    } else {
        format!("http://{address}")
    };
    let endpoint = Endpoint::from_shared(url.clone())
        .map_err(|e| anyhow!("{flag} {address:?} is not an address: {e}"))?
        .connect_timeout(TIMEOUT);
    endpoint.connect().await.map_err(|e| {
        let cause = std::error::Error::source(&e).map_or_else(|| e.to_string(), ToString::to_string);
        anyhow!(
            "cannot reach the {what} at {url}: {cause}\n  is it running, and listening there? set the address with {flag} (or its environment variable)"
        )
    })
}

/// A failed call as an error that names the call and explains the code.
pub fn call_error(what: &str, status: tonic::Status) -> anyhow::Error {
    use tonic::Code;
    let hint = match status.code() {
        Code::Unavailable => "the service went away; check that it is still running",
        Code::FailedPrecondition => "the service is not in a state to do that now",
        Code::InvalidArgument => "the request was refused as malformed",
        Code::NotFound => "no such thing on the service",
        Code::Unauthenticated => "the service wants a token",
        Code::PermissionDenied => "the token's role does not allow this",
        Code::DeadlineExceeded => "the service did not answer in time",
        _ => "",
    };
    let message = status.message();
    if hint.is_empty() {
        anyhow!("{what} failed: {:?}: {message}", status.code())
    } else {
        anyhow!("{what} failed: {message} ({hint})")
    }
}
