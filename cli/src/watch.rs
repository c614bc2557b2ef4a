//! Printing a status once, or again every few seconds (`--watch`).

use crate::fields::{self, Fields};
use std::io::IsTerminal;
use std::time::Duration;

/// The shortest `--watch` period.
const MIN_PERIOD: Duration = Duration::from_millis(100);

/// Prints what `poll` returns, once or every `watch` seconds until the
/// process is interrupted; on a terminal the screen is redrawn, otherwise
/// (and with `--json`) each poll is printed after the last.
pub async fn repeat<F, Fut>(watch: Option<f64>, json: bool, mut poll: F) -> anyhow::Result<()>
where
    F: FnMut() -> Fut,
    Fut: Future<Output = anyhow::Result<Fields>>,
{
    let Some(seconds) = watch else {
        fields::print(&poll().await?, json);
        return Ok(());
    };
    if !(seconds.is_finite() && seconds > 0.0) {
        anyhow::bail!("--watch {seconds}: give a period in seconds, above 0");
    }
    let period = Duration::from_secs_f64(seconds).max(MIN_PERIOD);
    let redraw = !json && std::io::stdout().is_terminal();
    loop {
        let fields = poll().await?;
        if redraw {
            print!("\x1b[2J\x1b[H");
        }
        fields::print(&fields, json);
        if !json && !redraw {
            println!();
        }
        tokio::time::sleep(period).await;
    }
}
