//! Turns SIGINT and SIGTERM into the cancellation of one [`CancellationToken`] that every task watches.

use tokio_util::sync::CancellationToken;
use tracing::info;

/// Spawns a task that cancels `token` on the first SIGINT or SIGTERM (and returns when `token` is
/// cancelled for another reason).
pub fn on_signals(token: CancellationToken) -> std::io::Result<tokio::task::JoinHandle<()>> {
    use tokio::signal::unix::{signal, SignalKind};
    let mut term = signal(SignalKind::terminate())?;
    let mut int = signal(SignalKind::interrupt())?;
    Ok(tokio::spawn(async move {
        tokio::select! {
            _ = term.recv() => info!("SIGTERM: shutting down"),
            _ = int.recv() => info!("SIGINT: shutting down"),
            _ = token.cancelled() => return,
        }
        token.cancel();
    }))
}
