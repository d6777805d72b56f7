//! Admission of `/localize` requests: first come, first served, with a bounded queue and a
//! bounded wait.
//!
//! At most `queue` localizations are admitted at once (running or waiting); one more gets 503
//! `queue_full` at once. Of the admitted ones, at most `running` (the CPU pool's threads)
//! compute; the others wait in arrival order (tokio's semaphore is fair) for at most
//! `max_wait`, then get 503 `queue_full` too — so a request that was admitted is never the
//! one that later runs into the request timeout because others overtook it, and no client
//! waits longer than `max_wait` for its turn.

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// The localize queue.
#[derive(Debug)]
pub struct Admission {
    admitted: Arc<Semaphore>,
    running: Arc<Semaphore>,
    max_wait: Duration,
}

/// Held while a localization computes; dropping it lets the next one in.
#[derive(Debug)]
pub struct Turn {
    _admitted: OwnedSemaphorePermit,
    _running: OwnedSemaphorePermit,
}

/// Why a request was not admitted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refusal {
    /// `queue` requests are already running or waiting.
    Full,
    /// The request waited `max_wait` without its turn coming.
    Waited,
}

impl Admission {
    /// A queue of `queue` requests of which `running` compute at once (both at least 1).
    pub fn new(queue: usize, running: usize, max_wait: Duration) -> Self {
        let queue = queue.max(1);
        Admission {
            admitted: Arc::new(Semaphore::new(queue)),
            running: Arc::new(Semaphore::new(running.clamp(1, queue))),
            max_wait,
        }
    }

    /// Waits for this request's turn, in arrival order.
    pub async fn enter(&self) -> Result<Turn, Refusal> {
        let admitted = Arc::clone(&self.admitted)
            .try_acquire_owned()
            .map_err(|_| Refusal::Full)?;
        let running = tokio::time::timeout(self.max_wait, Arc::clone(&self.running).acquire_owned())
            .await
            .map_err(|_| Refusal::Waited)?
            .map_err(|_| Refusal::Full)?;
        Ok(Turn {
            _admitted: admitted,
            _running: running,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    #[tokio::test]
    async fn turns_come_in_arrival_order() {
        let q = Arc::new(Admission::new(8, 1, Duration::from_secs(30)));
        let first = q.enter().await.unwrap();
        let order = Arc::new(Mutex::new(Vec::new()));
        let mut tasks = Vec::new();
        for i in 0..5 {
            let (q, order) = (Arc::clone(&q), Arc::clone(&order));
            tasks.push(tokio::spawn(async move {
                let turn = q.enter().await.unwrap();
                order.lock().unwrap().push(i);
                tokio::task::yield_now().await;
                drop(turn);
            }));
            // Let task i queue up before task i + 1 arrives.
            for _ in 0..10 {
                tokio::task::yield_now().await;
            }
        }
        drop(first);
        for t in tasks {
            t.await.unwrap();
        }
        assert_eq!(*order.lock().unwrap(), vec![0, 1, 2, 3, 4]);
    }

    #[tokio::test]
    async fn a_full_queue_refuses_at_once_and_a_long_wait_is_bounded() {
        let q = Admission::new(2, 1, Duration::from_millis(50));
        let running = q.enter().await.unwrap();
        // The second is admitted but waits, and gives up after `max_wait`.
        let waited = tokio::time::timeout(Duration::from_secs(10), q.enter()).await;
        assert_eq!(waited.unwrap().unwrap_err(), Refusal::Waited);
        // While one waits, a third finds the queue full.
        let q = Arc::new(q);
        let q2 = Arc::clone(&q);
        let waiter = tokio::spawn(async move { q2.enter().await.map(|_| ()) });
        for _ in 0..10 {
            tokio::task::yield_now().await;
        }
        assert_eq!(q.enter().await.unwrap_err(), Refusal::Full);
        drop(running);
        assert!(waiter.await.unwrap().is_ok());
    }
}
