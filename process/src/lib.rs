//! What every process binary of the workspace shares: logging to stderr,
//! the signals that stop it, and argument parsers.

use tracing_subscriber::EnvFilter;

/// Logs to stderr, filtered by `RUST_LOG` (default `info`); JSON lines for
/// log collectors when `json`.
pub fn init_logging(json: bool) {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()));
    if json {
        builder.json().init();
    } else {
        builder.init();
    }
}

/// Waits for SIGINT or SIGTERM (Ctrl-C elsewhere); names the one that came.
pub async fn stop_signal() -> &'static str {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => tokio::select! {
                _ = tokio::signal::ctrl_c() => "SIGINT",
                _ = term.recv() => "SIGTERM",
            },
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
                "SIGINT"
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
        "Ctrl-C"
    }
}

/// Parses "X,Y" into two finite numbers (a clap value parser).
pub fn parse_pair(text: &str) -> Result<[f64; 2], String> {
    let parse = |p: &str| {
        p.trim()
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite())
            .ok_or_else(|| format!("{p:?} is not a finite number"))
    };
    match text.split(',').collect::<Vec<_>>().as_slice() {
        [x, y] => Ok([parse(x)?, parse(y)?]),
        _ => Err(format!("{text:?}: expected two numbers, X,Y")),
    }
}

#[cfg(test)]
mod tests {
    use super::parse_pair;

    #[test]
    fn pairs_parse_and_bad_ones_are_named() {
        assert_eq!(parse_pair("1.5, -2"), Ok([1.5, -2.0]));
        assert!(
            parse_pair("1")
                .unwrap_err()
                .contains("expected two numbers")
        );
        assert!(
            parse_pair("1,inf")
                .unwrap_err()
                .contains("\"inf\" is not a finite number")
        );
    }
}
