//! Admission of `/localize` requests: a bounded queue in front of the CPU pool, first come
//! first served, with a bounded wait.
//!
//! Two steps, so that a slow upload never holds a place or a CPU turn (and the turn ends with
//! the computation, before the result is stored, so that a slow disk never holds one either):
//!
//! 1. [`Admission::reserve`], once the map is checked and the body is read and parsed: at most
//!    `queue` localizations are in the queue at once (waiting or computing); one more is
//!    refused at once ([`Refusal::Full`]). A client that trickles its body holds no place.
//! 2. [`Reservation::turn`], once the request is parsed: at most `running` localizations
//!    compute at once (the CPU pool's threads); the others wait in arrival order (tokio's
//!    semaphore is fair) for at most `max_wait`. A request whose estimated wait — the
//!    requests ahead of it times the recent duration of a turn ([`Turn::finish`] records it),
//!    divided by `running` — exceeds `max_wait` is refused at once ([`Refusal::Busy`]); one
//!    that still waits `max_wait` (the estimate was too low) is refused then
//!    ([`Refusal::Waited`]).
//!
//! `max_wait` is below the request timeout (checked in `config`), so a request that gets its
//! turn is never the one that later runs into the timeout because others overtook it, and
//! every refusal carries a `Retry-After` from the same estimate; before any turn was measured,
//! and after a wait of `max_wait` in vain, it is `max_wait` (the queue may be held that long),
//! never a hopeful 1 s.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// Weight of the newest turn in the running estimate of a turn's duration.
const EWMA_WEIGHT: f64 = 0.2;

/// The localize queue. Share it behind an `Arc`.
#[derive(Debug)]
pub struct Admission {
    queued: Arc<Semaphore>,
    /// Places in the queue.
    capacity: usize,
    running: Arc<Semaphore>,
    threads: usize,
    max_wait: Duration,
    /// Requests waiting for a turn right now.
    waiting: AtomicUsize,
    /// Requests that asked for a turn since start (for metrics and tests).
    arrivals: AtomicU64,
    /// Recent duration of a turn in seconds (exponentially weighted), `None` before the first.
    turn_secs: Mutex<Option<f64>>,
}

/// A place in the queue, held from the parsed request until its turn ends.
#[derive(Debug)]
pub struct Reservation {
    admission: Arc<Admission>,
    _queued: OwnedSemaphorePermit,
}

/// Held while a localization computes; dropping it lets the next one in.
#[derive(Debug)]
pub struct Turn {
    admission: Arc<Admission>,
    started: Instant,
    _queued: OwnedSemaphorePermit,
    _running: OwnedSemaphorePermit,
}

/// Why a request was not admitted; each says when to retry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refusal {
    /// `queue` requests are already queued.
    Full {
        /// Suggested `Retry-After` in seconds.
        retry_after: u64,
    },
    /// The request would wait longer than `max_wait` (estimated when it arrived).
    Busy {
        /// Suggested `Retry-After` in seconds (the estimated wait).
        retry_after: u64,
    },
    /// The request waited `max_wait` without its turn coming.
    Waited {
        /// Suggested `Retry-After` in seconds.
        retry_after: u64,
    },
}

impl Refusal {
    /// Seconds the client should wait before retrying (at least 1).
    pub fn retry_after(self) -> u64 {
        match self {
            Refusal::Full { retry_after }
            | Refusal::Busy { retry_after }
            | Refusal::Waited { retry_after } => retry_after.max(1),
        }
    }
}

impl Admission {
    /// A queue of `queue` requests of which `running` compute at once (both at least 1), and
    /// a wait of at most `max_wait`.
    pub fn new(queue: usize, running: usize, max_wait: Duration) -> Self {
        let queue = queue.max(1);
        let threads = running.clamp(1, queue);
        Admission {
            queued: Arc::new(Semaphore::new(queue)),
            capacity: queue,
            running: Arc::new(Semaphore::new(threads)),
            threads,
            max_wait,
            waiting: AtomicUsize::new(0),
            arrivals: AtomicU64::new(0),
            turn_secs: Mutex::new(None),
        }
    }

    /// Takes a place in the queue, or refuses at once when it is full.
    pub fn reserve(self: &Arc<Self>) -> Result<Reservation, Refusal> {
        let queued = Arc::clone(&self.queued)
            .try_acquire_owned()
            .map_err(|_| Refusal::Full {
                retry_after: self.retry_secs(self.waiting.load(Ordering::Relaxed)),
            })?;
        Ok(Reservation {
            admission: Arc::clone(self),
            _queued: queued,
        })
    }

    /// Requests holding a place in the queue now (waiting or computing).
    pub fn depth(&self) -> usize {
        self.capacity
            .saturating_sub(self.queued.available_permits())
    }

    /// Requests waiting for a turn now.
    pub fn waiting(&self) -> usize {
        self.waiting.load(Ordering::Relaxed)
    }

    /// Requests that asked for a turn since start.
    pub fn arrivals(&self) -> u64 {
        self.arrivals.load(Ordering::Relaxed)
    }

    /// The recent duration of a turn, if any turn finished yet.
    fn turn_estimate(&self) -> Option<f64> {
        *self.turn_secs.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Estimated wait of a request with `ahead` requests waiting before it while every CPU
    /// turn is taken: `ahead + 1` turns must end, `threads` at a time.
    fn estimated_wait(&self, ahead: usize) -> Option<Duration> {
        let turn = self.turn_estimate()?;
        let secs = turn * (ahead + 1) as f64 / self.threads as f64;
        Some(Duration::from_secs_f64(secs.clamp(0.0, 1e9)))
    }

    /// `Retry-After` for a request refused with `ahead` requests waiting: the estimated wait
    /// (at least 1 s), or `max_wait` before any turn was measured (nothing says the queue
    /// frees sooner: each queued request may wait that long).
    fn retry_secs(&self, ahead: usize) -> u64 {
        self.estimated_wait(ahead).map_or_else(
            || self.max_wait_secs(),
            |wait| wait.as_secs_f64().ceil().max(1.0) as u64,
        )
    }

    /// `max_wait` in whole seconds, at least 1.
    fn max_wait_secs(&self) -> u64 {
        self.max_wait.as_secs_f64().ceil().max(1.0) as u64
    }

    fn record(&self, secs: f64) {
        let mut est = self.turn_secs.lock().unwrap_or_else(|e| e.into_inner());
        *est = Some(match *est {
            None => secs,
            Some(old) => old + EWMA_WEIGHT * (secs - old),
        });
    }
}

impl Reservation {
    /// Waits for this request's turn, in arrival order, for at most `max_wait`; refuses at
    /// once when the estimated wait is longer.
    pub async fn turn(self) -> Result<Turn, Refusal> {
        let Reservation { admission, _queued } = self;
        admission.arrivals.fetch_add(1, Ordering::Relaxed);
        let running = match Arc::clone(&admission.running).try_acquire_owned() {
            Ok(permit) => permit,
            Err(_) => {
                let ahead = admission.waiting.load(Ordering::Relaxed);
                if let Some(wait) = admission.estimated_wait(ahead) {
                    if wait > admission.max_wait {
                        return Err(Refusal::Busy {
                            retry_after: wait.as_secs_f64().ceil() as u64,
                        });
                    }
                }
                let _waiting = Waiting::new(&admission.waiting);
                let acquire = Arc::clone(&admission.running).acquire_owned();
                match tokio::time::timeout(admission.max_wait, acquire).await {
                    Ok(Ok(permit)) => permit,
                    // The semaphore is never closed; treat it as a full queue if it were.
                    // Having waited `max_wait` in vain, the queue is held at least that long.
                    Ok(Err(_)) | Err(_) => {
                        return Err(Refusal::Waited {
                            retry_after: admission.retry_secs(ahead).max(admission.max_wait_secs()),
                        })
                    }
                }
            }
        };
        Ok(Turn {
            admission,
            started: Instant::now(),
            _queued,
            _running: running,
        })
    }
}

impl Turn {
    /// Ends the turn of a localization whose computation ran to its end, recording how long
    /// it took (a turn dropped without this, e.g. a failed or cancelled request, is not
    /// counted). Called when the result is computed, before it is stored
    /// ([`seasonloc_app::App::localize`]): a turn is CPU time.
    pub fn finish(self) {
        self.admission.record(self.started.elapsed().as_secs_f64());
    }
}

/// Counts a waiting request for as long as it lives (also when the request is cancelled).
struct Waiting<'a>(&'a AtomicUsize);

impl<'a> Waiting<'a> {
    fn new(n: &'a AtomicUsize) -> Self {
        n.fetch_add(1, Ordering::Relaxed);
        Waiting(n)
    }
}

impl Drop for Waiting<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    async fn settle() {
        for _ in 0..20 {
            tokio::task::yield_now().await;
        }
    }

    #[tokio::test]
    async fn turns_come_in_arrival_order() {
        let q = Arc::new(Admission::new(16, 1, Duration::from_secs(30)));
        let first = q.reserve().unwrap().turn().await.unwrap();
        let order = Arc::new(Mutex::new(Vec::new()));
        let mut tasks = Vec::new();
        for i in 0..8 {
            let (q2, order) = (Arc::clone(&q), Arc::clone(&order));
            tasks.push(tokio::spawn(async move {
                let turn = q2.reserve().unwrap().turn().await.unwrap();
                order.lock().unwrap().push(i);
                tokio::task::yield_now().await;
                turn.finish();
            }));
            // Task i waits before task i + 1 arrives.
            settle().await;
            assert_eq!(q.waiting(), i + 1);
        }
        drop(first);
        for t in tasks {
            t.await.unwrap();
        }
        assert_eq!(*order.lock().unwrap(), (0..8).collect::<Vec<_>>());
        assert_eq!(q.waiting(), 0);
        assert_eq!(q.arrivals(), 9);
    }

    #[tokio::test]
    async fn a_full_queue_refuses_at_once() {
        let q = Arc::new(Admission::new(2, 1, Duration::from_secs(30)));
        let _a = q.reserve().unwrap();
        let _b = q.reserve().unwrap();
        let refused = q.reserve().unwrap_err();
        assert!(matches!(refused, Refusal::Full { .. }), "{refused:?}");
        assert!(refused.retry_after() >= 1);
    }

    #[tokio::test]
    async fn a_full_queue_never_claims_a_second_before_anything_is_known() {
        // Nothing measured yet: the queue may be held for `max_wait` by each waiter.
        let q = Arc::new(Admission::new(2, 1, Duration::from_secs(30)));
        let _a = q.reserve().unwrap();
        let _b = q.reserve().unwrap();
        assert_eq!(q.reserve().unwrap_err().retry_after(), 30);
        // Once turns are measured, the estimate says it.
        q.record(4.0);
        assert_eq!(q.reserve().unwrap_err().retry_after(), 4);
    }

    #[tokio::test]
    async fn a_wait_is_bounded_when_nothing_is_known_yet() {
        let q = Arc::new(Admission::new(4, 1, Duration::from_millis(50)));
        let running = q.reserve().unwrap().turn().await.unwrap();
        let started = Instant::now();
        let refused = q.reserve().unwrap().turn().await.unwrap_err();
        assert!(matches!(refused, Refusal::Waited { .. }), "{refused:?}");
        assert!(started.elapsed() >= Duration::from_millis(50));
        // It waited the whole bound in vain: retry no sooner than that (rounded up to 1 s).
        assert_eq!(refused.retry_after(), 1);
        assert_eq!(q.waiting(), 0);
        drop(running);
        // The place and the turn were given back.
        assert!(q.reserve().unwrap().turn().await.is_ok());
    }

    #[tokio::test]
    async fn a_request_that_would_wait_too_long_is_refused_at_once() {
        let q = Arc::new(Admission::new(16, 2, Duration::from_secs(9)));
        // Turns have taken 4 s each.
        q.record(4.0);
        let _a = q.reserve().unwrap().turn().await.unwrap();
        let _b = q.reserve().unwrap().turn().await.unwrap();
        // Waiters 1..=4 are estimated at 2, 4, 6, 8 s (at most 9): they wait.
        let mut waiters = Vec::new();
        for _ in 0..4 {
            let q2 = Arc::clone(&q);
            waiters.push(tokio::spawn(async move {
                q2.reserve().unwrap().turn().await.map(Turn::finish)
            }));
            settle().await;
        }
        assert_eq!(q.waiting(), 4);
        // The fifth would wait 10 s (2 turns per 4 s): refused without waiting.
        // Refused without waiting (a wait would last the 9 s bound).
        let refused = tokio::time::timeout(Duration::from_secs(5), async {
            q.reserve().unwrap().turn().await.unwrap_err()
        })
        .await
        .unwrap();
        assert_eq!(refused, Refusal::Busy { retry_after: 10 });
        assert_eq!(q.waiting(), 4);
        drop((_a, _b));
        for w in waiters {
            assert!(w.await.unwrap().is_ok());
        }
    }

    #[tokio::test]
    async fn finished_turns_update_the_estimate() {
        let q = Arc::new(Admission::new(4, 1, Duration::from_secs(10)));
        assert_eq!(q.turn_estimate(), None);
        let t = q.reserve().unwrap().turn().await.unwrap();
        tokio::time::sleep(Duration::from_millis(30)).await;
        t.finish();
        let est = q.turn_estimate().unwrap();
        assert!(est >= 0.03, "{est}");
        // A dropped (cancelled or failed) turn does not count.
        let t = q.reserve().unwrap().turn().await.unwrap();
        tokio::time::sleep(Duration::from_millis(30)).await;
        drop(t);
        assert_eq!(q.turn_estimate(), Some(est));
        // Later turns move the estimate by a fifth of the difference.
        q.record(est + 5.0);
        let moved = q.turn_estimate().unwrap();
        assert!((moved - (est + 1.0)).abs() < 1e-9, "{moved}");
    }
}
