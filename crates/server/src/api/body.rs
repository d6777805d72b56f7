//! Request bodies with a bound in time: [`deadline`], the middleware that gives every request
//! body a deadline for arriving whole (`--body-deadline-secs`). The gap timeout between bytes
//! (`--body-read-timeout-secs`) alone lets one byte every few seconds hold a request, and
//! whatever it holds, until the request timeout. Past the deadline the next read fails with
//! [`BodyDeadlineExceeded`], which the extractors answer 408 `body_timeout`
//! ([`super::extract::is_body_timeout`]).

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
}
