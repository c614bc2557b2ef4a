//! Connecting to a service, with errors that say what to do about them.

use anyhow::anyhow;
use std::path::Path;
use std::time::Duration;
use tweezer_rpc::{AuthChannel, ClientSecurity, ConnectError, Security};

/// How long a connection attempt may take.
const TIMEOUT: Duration = Duration::from_secs(10);

/// A channel to `address` (`host:port` or a URL) secured as the security
/// file `security` (or `TWEEZER_SECURITY`) says; `what` names the service
/// in errors, `flag` the option that sets its address.
pub async fn channel(
    security: Option<&Path>,
    address: &str,
    what: &str,
    flag: &str,
) -> anyhow::Result<AuthChannel> {
    let client = ClientSecurity::load(&Security::load(security)?)?;
    client.connect(address, TIMEOUT).await.map_err(|e| match e {
        ConnectError::Address { .. } => anyhow!("{flag}: {e}"),
        ConnectError::Unreachable { .. } => {
            anyhow!("the {what}: {e}\n  set its address with {flag} (or its environment variable)")
        }
    })
}

/// Prints the health of `service` at `address`; an error unless SERVING.
pub async fn health(security: Option<&Path>, address: &str, service: &str) -> anyhow::Result<()> {
    let client = ClientSecurity::anonymous(&Security::load(security)?)?;
    let status = client.health(address, service, TIMEOUT).await?;
    println!("{status}");
    if status == "SERVING" {
        Ok(())
    } else {
        Err(anyhow!("{address} is {status}"))
    }
}

/// A failed call as an error that names the call and explains the code.
/// A status the service itself answered with is its own account of what
/// went wrong (a learner the agent cannot reach, say); one the transport
/// made (it carries its cause) is about reaching the service.
pub fn call_error(what: &str, status: tonic::Status) -> anyhow::Error {
    use tonic::Code;
    let message = status.message();
    let from_transport = std::error::Error::source(&status).is_some();
    let hint = match status.code() {
        Code::Unavailable if from_transport => tweezer_rpc::hint(message, false)
            .unwrap_or("the service went away; check that it is still running"),
        Code::Unavailable => {
            "the service cannot reach what it needs for that now; try again once it is back"
        }
        Code::FailedPrecondition => "the service is not in a state to do that now",
        Code::InvalidArgument => {
            "the service refused the request as it stands: change what the message names"
        }
        Code::NotFound => "no such thing on the service",
        Code::Unauthenticated => {
            "the service does not accept this token: check the security file's token_file or TWEEZER_TOKEN"
        }
        Code::PermissionDenied => {
            "use a token with the role named (`tweezer token new --role ...` issues one)"
        }
        Code::DeadlineExceeded => "the service did not answer in time",
        _ => "",
    };
    if hint.is_empty() {
        anyhow!("{what} failed: {:?}: {message}", status.code())
    } else {
        anyhow!("{what} failed: {message}\n  {hint}")
    }
}
