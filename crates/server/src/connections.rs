//! The connection cap (`--max-connections`): at most `max` connections are served at once, so
//! the process never runs out of file descriptors (which would stop it accepting anyone,
//! probes included).
//!
//! At the cap a new connection is still accepted, and the connection that has waited longest
//! for a request header is closed in its place: one that sent half a header and stopped, or a
//! kept-alive one between requests. A client holding many half-open connections thus only
//! ever displaces its own oldest ones, while a probe (which sends its request at once) gets
//! its answer. When every connection is busy with a request, the new one is closed instead.
//! The accept loop waits for a connection it displaced to be closed ([`Displaced::closed`])
//! before it accepts the next, so the descriptors in use stay at the cap (plus one) however fast
//! connections arrive.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use tokio::sync::{oneshot, Notify};

/// The live connections. Share it behind an `Arc`.
#[derive(Debug)]
pub struct ConnectionCap {
    max: usize,
    inner: Mutex<Inner>,
}

#[derive(Debug, Default)]
struct Inner {
    next: u64,
    /// Live connections by age (oldest first).
    live: BTreeMap<u64, Entry>,
    /// Connections closed to make room since start.
    evicted: u64,
}

#[derive(Debug)]
struct Entry {
    waiting: Arc<AtomicBool>,
    close: Arc<Notify>,
    /// Completes when the connection's [`Slot`] is dropped (its socket closed).
    closed: oneshot::Receiver<()>,
}

/// A connection told to close to make room; [`Displaced::closed`] waits until it has.
#[derive(Debug)]
pub struct Displaced(oneshot::Receiver<()>);

impl Displaced {
    /// Completes once the displaced connection is closed.
    pub async fn closed(self) {
        // The sender is never used: its drop, with the slot's, is the signal.
        let _ = self.0.await;
    }
}

/// One admitted connection: its state, and its place under the cap until it is dropped.
#[derive(Debug)]
pub struct Slot {
    cap: Arc<ConnectionCap>,
    id: u64,
    /// Whether the connection is waiting for a request header (no request in progress).
    waiting: Arc<AtomicBool>,
    /// Notified when the connection must close to make room.
    close: Arc<Notify>,
    /// Dropped with the slot, once the connection is closed.
    _closed: oneshot::Sender<()>,
}

impl ConnectionCap {
    /// A cap of `max` connections (at least 1).
    pub fn new(max: usize) -> Self {
        ConnectionCap {
            max: max.max(1),
            inner: Mutex::new(Inner::default()),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A slot for a new connection: at the cap, the oldest connection waiting for a request
    /// header is told to close and gives up its slot (returned, to wait for it to be closed);
    /// `None` when every connection is busy.
    pub fn admit(self: &Arc<Self>) -> Option<(Slot, Option<Displaced>)> {
        let mut inner = self.lock();
        let mut displaced = None;
        if inner.live.len() >= self.max {
            let oldest_waiting = inner
                .live
                .iter()
                .find(|(_, e)| e.waiting.load(Ordering::Relaxed))
                .map(|(&id, _)| id);
            let entry = inner.live.remove(&oldest_waiting?)?;
            entry.close.notify_one();
            inner.evicted += 1;
            displaced = Some(Displaced(entry.closed));
        }
        let id = inner.next;
        inner.next += 1;
        let waiting = Arc::new(AtomicBool::new(true));
        let close = Arc::new(Notify::new());
        let (closed_tx, closed_rx) = oneshot::channel();
        inner.live.insert(
            id,
            Entry {
                waiting: Arc::clone(&waiting),
                close: Arc::clone(&close),
                closed: closed_rx,
            },
        );
        let slot = Slot {
            cap: Arc::clone(self),
            id,
            waiting,
            close,
            _closed: closed_tx,
        };
        Some((slot, displaced))
    }

    /// Connections served now.
    pub fn live(&self) -> usize {
        self.lock().live.len()
    }

    /// Connections closed to make room since start.
    pub fn evicted(&self) -> u64 {
        self.lock().evicted
    }

    /// The cap.
    pub fn max(&self) -> usize {
        self.max
    }
}

impl Slot {
    /// The flag "waiting for a request header", to clear when a request starts and set again
    /// once its response has been sent.
    pub fn waiting(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.waiting)
    }

    /// Completes when the connection must close to make room for a newer one.
    pub async fn evicted(&self) {
        self.close.notified().await;
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        self.cap.lock().live.remove(&self.id);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[tokio::test]
    async fn at_the_cap_the_oldest_waiting_connection_makes_room() {
        let cap = Arc::new(ConnectionCap::new(3));
        let admit = |cap: &Arc<ConnectionCap>| cap.admit().map(|(slot, _)| slot);
        let a = admit(&cap).unwrap();
        let b = admit(&cap).unwrap();
        let c = admit(&cap).unwrap();
        // `a` is busy with a request: `b`, the oldest waiting one, is closed for `d`.
        a.waiting().store(false, Ordering::Relaxed);
        let (d, displaced) = cap.admit().unwrap();
        let displaced = displaced.expect("b made room");
        assert_eq!(cap.live(), 3);
        assert_eq!(cap.evicted(), 1);
        tokio::time::timeout(Duration::from_secs(1), b.evicted())
            .await
            .expect("b was told to close");
        assert!(
            tokio::time::timeout(Duration::from_millis(20), c.evicted())
                .await
                .is_err(),
            "c stays"
        );
        // Once b's slot is dropped (its connection closed), the accept loop may go on; that
        // does not free a second place.
        drop(b);
        tokio::time::timeout(Duration::from_secs(1), displaced.closed())
            .await
            .expect("b's close is seen");
        assert_eq!(cap.live(), 3);
        // All busy: a new connection is refused.
        c.waiting().store(false, Ordering::Relaxed);
        d.waiting().store(false, Ordering::Relaxed);
        assert!(cap.admit().is_none());
        drop(c);
        assert!(cap.admit().is_some());
    }
}
