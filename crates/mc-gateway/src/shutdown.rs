//! Turns SIGINT and SIGTERM into the cancellation of one [`CancellationToken`] that every task
//! watches, and gives the tasks' loops that cancellation as a future cheap to poll at every turn.

use std::future::Future;
use std::pin::Pin;
use std::task::{ready, Context, Poll};

use tokio::sync::oneshot;
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

/// `token`'s cancellation as a future that costs little to poll again and again.
///
/// tokio-util's `WaitForCancellationFuture` polls a `Notify` waiter, which takes the token's lock at
/// every poll, and the gateway's loops poll their stop branch at every turn beside their inputs:
/// about eight times per command, ~150 instructions each (callgrind). This one waits on a oneshot
/// channel whose sender a task holds until `token` is cancelled: a poll that finds it open is an
/// atomic load and a waker comparison. The task also ends when the [`Stopped`] is dropped.
pub fn stopped(token: &CancellationToken) -> Stopped {
    let (mut tx, rx) = oneshot::channel::<()>();
    let token = token.clone();
    tokio::spawn(async move {
        tokio::select! {
            _ = token.cancelled() => {}
            _ = tx.closed() => {}
        }
    });
    Stopped(Some(rx))
}

/// Ready once the token given to [`stopped`] is cancelled (and at every poll after that).
#[derive(Debug)]
pub struct Stopped(Option<oneshot::Receiver<()>>);

impl Future for Stopped {
    type Output = ();

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<()> {
        let Some(rx) = self.0.as_mut() else {
            return Poll::Ready(());
        };
        // Nothing is ever sent: the sender dropped is the signal.
        let _ = ready!(Pin::new(rx).poll(cx));
        self.0 = None;
        Poll::Ready(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[tokio::test]
    async fn stopped_is_ready_once_the_token_is_cancelled_and_stays_ready() {
        let token = CancellationToken::new();
        let mut stop = stopped(&token);
        let waited = tokio::time::timeout(Duration::from_millis(50), &mut stop).await;
        assert!(waited.is_err(), "ready before the cancellation");
        token.cancel();
        tokio::time::timeout(Duration::from_secs(1), &mut stop)
            .await
            .expect("not ready after the cancellation");
        tokio::time::timeout(Duration::from_secs(1), &mut stop)
            .await
            .expect("not ready at the next poll");
    }

    #[tokio::test]
    async fn a_token_cancelled_before_is_seen_at_once() {
        let token = CancellationToken::new();
        token.cancel();
        tokio::time::timeout(Duration::from_secs(1), stopped(&token))
            .await
            .expect("not ready");
    }

    #[tokio::test(flavor = "current_thread")]
    async fn dropping_it_ends_its_task() {
        let token = CancellationToken::new();
        let tasks = tokio::runtime::Handle::current().metrics();
        let before = tasks.num_alive_tasks();
        let stop = stopped(&token);
        tokio::task::yield_now().await;
        assert_eq!(tasks.num_alive_tasks(), before + 1);
        drop(stop);
        for _ in 0..10 {
            tokio::task::yield_now().await;
        }
        assert_eq!(tasks.num_alive_tasks(), before, "its task outlived it");
    }
}
