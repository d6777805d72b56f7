//! Request and response bodies with a bound in time or a hook on their end:
//!
//! * [`deadline`], the middleware that gives every request body a deadline for arriving whole
//!   (`--body-deadline-secs`): the gap timeout between bytes (`--body-read-timeout-secs`) alone
//!   lets one byte every few seconds hold a request, and whatever it holds, until the request
//!   timeout. Past the deadline the next read fails with [`BodyDeadlineExceeded`], which the
//!   extractors answer 408 `body_timeout` ([`super::extract::is_body_timeout`]).
//! * [`OnDrop`], a body that runs a closure once it is dropped (sent whole, or abandoned): the
//!   connection cap marks a connection idle again with it.

use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, Bytes, HttpBody};
use axum::extract::{Request, State};
use axum::middleware::Next;
use axum::response::Response;
use hyper::body::{Frame, SizeHint};

/// The error of a body read after its deadline.
#[derive(Debug, thiserror::Error)]
#[error("the request body did not arrive whole within the server's deadline of {0:?}")]
pub struct BodyDeadlineExceeded(pub Duration);

/// A request body that fails once `limit` has passed since the request arrived.
struct DeadlineBody {
    inner: Body,
    limit: Duration,
    expires: Pin<Box<tokio::time::Sleep>>,
}

impl HttpBody for DeadlineBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        if self.expires.as_mut().poll(cx).is_ready() {
            let limit = self.limit;
            return Poll::Ready(Some(Err(axum::Error::new(BodyDeadlineExceeded(limit)))));
        }
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// Middleware: the request's body must arrive whole within `limit` of now (the end of its
/// header). A body already complete is left alone.
pub async fn deadline(State(limit): State<Duration>, req: Request, next: Next) -> Response {
    let (parts, body) = req.into_parts();
    let body = if body.is_end_stream() {
        body
    } else {
        Body::new(DeadlineBody {
            inner: body,
            limit,
            expires: Box::pin(tokio::time::sleep(limit)),
        })
    };
    next.run(Request::from_parts(parts, body)).await
}

/// A body that calls `on_drop` once, when it is dropped.
pub struct OnDrop<F: FnOnce()> {
    inner: Body,
    on_drop: Option<F>,
}

impl<F: FnOnce()> OnDrop<F> {
    /// `inner`, with `on_drop` to run when it is dropped.
    pub fn new(inner: Body, on_drop: F) -> Self {
        OnDrop {
            inner,
            on_drop: Some(on_drop),
        }
    }
}

impl<F: FnOnce()> Drop for OnDrop<F> {
    fn drop(&mut self) {
        if let Some(f) = self.on_drop.take() {
            f();
        }
    }
}

impl<F: FnOnce() + Unpin> HttpBody for OnDrop<F> {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A body whose next frame never comes (a client that stopped sending).
    struct Stalled;

    impl HttpBody for Stalled {
        type Data = Bytes;
        type Error = axum::Error;

        fn poll_frame(
            self: Pin<&mut Self>,
            _: &mut Context<'_>,
        ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
            Poll::Pending
        }
    }

    #[tokio::test]
    async fn a_body_past_its_deadline_fails_with_the_deadline_error() {
        let limit = Duration::from_millis(50);
        let mut body = DeadlineBody {
            inner: Body::new(Stalled),
            limit,
            expires: Box::pin(tokio::time::sleep(limit)),
        };
        let started = std::time::Instant::now();
        let next = std::future::poll_fn(|cx| Pin::new(&mut body).poll_frame(cx)).await;
        assert!(started.elapsed() >= limit);
        let err = next
            .and_then(Result::err)
            .expect("an error past the deadline");
        assert!(
            super::super::extract::is_body_timeout(&err),
            "{err}: not recognised as a body timeout"
        );
    }

    #[test]
    fn on_drop_runs_once() {
        let n = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let m = std::sync::Arc::clone(&n);
        let b = OnDrop::new(Body::empty(), move || {
            m.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        });
        drop(b);
        assert_eq!(n.load(std::sync::atomic::Ordering::Relaxed), 1);
    }
}
