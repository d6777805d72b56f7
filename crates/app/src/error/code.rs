//! The one table of error codes: every code a client can see, with its HTTP status and
//! whether the answer asks the client to retry (`Retry-After`), in the manner of
//! meilisearch's `Code`. Each layer's error says its code once (`StoreError::code`,
//! `AppError::code`, the server's `ApiError::code`); the status, the body and the OpenAPI's
//! list of codes (checked by a test) all come from here, so adding an error is one variant
//! where it is raised and, for a new code, one row below.

/// Defines [`ErrorCode`] from its rows: `Variant = "code", status[, retry][, hidden];`.
macro_rules! error_codes {
    ($( $(#[$doc:meta])* $variant:ident = $code:literal, $status:literal $(, $flag:ident)* ; )*) => {
        /// A stable, machine-readable error code (the `code` of the JSON error body).
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
        pub enum ErrorCode {
            $( $(#[$doc])* $variant, )*
        }

        impl ErrorCode {
            /// Every code, in the table's order.
            pub const ALL: &'static [ErrorCode] = &[$(ErrorCode::$variant),*];

            /// The snake_case code clients match on.
            pub fn as_str(self) -> &'static str {
                match self { $(ErrorCode::$variant => $code,)* }
            }

            /// The HTTP status of an answer with this code.
            pub fn status(self) -> u16 {
                match self { $(ErrorCode::$variant => $status,)* }
            }

            /// Whether the answer carries `Retry-After` (the request may succeed later).
            pub fn retry_after(self) -> bool {
                match self { $(ErrorCode::$variant => error_codes!(@has retry $($flag)*),)* }
            }

            /// Whether the message is for logs only: the client gets a fixed sentence, the
            /// cause (a path, a database address) is logged instead.
            pub fn hides_message(self) -> bool {
                match self { $(ErrorCode::$variant => error_codes!(@has hidden $($flag)*),)* }
            }
        }
    };
    (@has $want:ident) => { false };
    (@has retry retry $($rest:ident)*) => { true };
    (@has hidden hidden $($rest:ident)*) => { true };
    (@has $want:ident $other:ident $($rest:ident)*) => { error_codes!(@has $want $($rest)*) };
}

error_codes! {
    /// No map with this id.
    MapNotFound = "map_not_found", 404;
    /// No localization with this id.
    LocalizationNotFound = "localization_not_found", 404;
    /// No trip with this id.
    TripNotFound = "trip_not_found", 404;
    /// No such image, or an image stored without a thumbnail.
    ThumbnailNotFound = "thumbnail_not_found", 404;
    /// A localization stored without a similarity picture.
    PictureNotFound = "picture_not_found", 404;
    /// A dashboard file that does not exist.
    AssetNotFound = "asset_not_found", 404;
    /// No route for this path.
    RouteNotFound = "route_not_found", 404;
    /// The route exists, not with this method.
    MethodNotAllowed = "method_not_allowed", 405;
    /// An unknown, missing or out-of-range parameter.
    InvalidParameter = "invalid_parameter", 400;
    /// A malformed body (JSON syntax, multipart framing, unknown part).
    BadRequest = "bad_request", 400;
    /// Nothing to work on (no frames, no queries, no descriptors).
    EmptyBatch = "empty_batch", 400;
    /// More images or descriptors in one request than the configured limit, or a batch held
    /// decoded whole over the budget of decoded pixels.
    BatchTooLarge = "batch_too_large", 400;
    /// No key, or a key the service does not know (`WWW-Authenticate: Bearer`).
    Unauthorized = "unauthorized", 401;
    /// A known key whose role does not allow the request.
    Forbidden = "forbidden", 403;
    /// A state-changing request to a server without API keys that a browser sent for another
    /// site (a cross-site `Origin` or `Sec-Fetch-Site`) without `X-Requested-With`.
    CrossSiteRequest = "cross_site_request", 403;
    /// The request body stalled longer than the server's body read timeout, or did not arrive
    /// whole within its deadline.
    BodyTimeout = "body_timeout", 408;
    /// Frames posted to a closed trip.
    TripClosed = "trip_closed", 409;
    /// The trip changed while a batch was computed (retry the batch).
    TripConflict = "trip_conflict", 409;
    /// Localizing against a map without reference images.
    MapEmpty = "map_empty", 409;
    /// The map cannot hold more images.
    MapFull = "map_full", 409;
    /// A CNN map's model file is no longer the model the map was created with.
    ModelMismatch = "model_mismatch", 409;
    /// The request does not apply to this kind of map.
    MapKind = "map_kind", 409;
    /// A concurrent request changed the map first; retrying is safe.
    MapChanged = "map_changed", 409;
    /// An `Idempotency-Key` sent again with a different request.
    IdempotencyKeyReused = "idempotency_key_reused", 409;
    /// The body exceeds the configured size limit.
    PayloadTooLarge = "payload_too_large", 413;
    /// An image exceeds the configured pixel limit.
    ImageTooLarge = "image_too_large", 413;
    /// A body of a media type the route does not take.
    UnsupportedMediaType = "unsupported_media_type", 415;
    /// A `Host` header that is not an allowed host.
    MisdirectedRequest = "misdirected_request", 421;
    /// A parameter valid on its own that does not fit the request's other parameters, the
    /// server's limits or the model it names (a rule a schema of single fields cannot state).
    InconsistentParameter = "inconsistent_parameter", 422;
    /// A part that is not a decodable JPEG/PNG.
    InvalidImage = "invalid_image", 422;
    /// Descriptors (or images giving them) that do not fit the map.
    DescriptorLength = "descriptor_length", 422;
    /// NaN or infinity in the input.
    NonFinite = "non_finite", 422;
    /// Inputs whose shapes do not fit together.
    ShapeMismatch = "shape_mismatch", 422;
    /// The key has its limit of requests in flight.
    TooManyRequests = "too_many_requests", 429, retry;
    /// A bug or a broken store.
    Internal = "internal", 500, hidden;
    /// The localize queue is full, or the request would wait too long for a CPU.
    QueueFull = "queue_full", 503, retry;
    /// The server is at its concurrency limit.
    Overloaded = "overloaded", 503, retry;
    /// The request took longer than the configured timeout.
    Timeout = "timeout", 503, retry;
    /// The store cannot be reached now.
    NotReady = "not_ready", 503, retry, hidden;
    /// The store's disk is full: the write was not stored; reads still work, and writes
    /// succeed again once space is freed (no restart needed).
    StorageFull = "storage_full", 507, retry;
}

impl std::fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_are_unique_snake_case_with_an_error_status() {
        let mut seen = std::collections::BTreeSet::new();
        for c in ErrorCode::ALL {
            assert!(seen.insert(c.as_str()), "{c} twice");
            assert!(
                c.as_str()
                    .bytes()
                    .all(|b| b.is_ascii_lowercase() || b == b'_'),
                "{c}"
            );
            assert!((400..600).contains(&c.status()), "{c}");
            // Retry-After belongs to answers that can succeed later.
            assert!(
                !c.retry_after() || matches!(c.status(), 429 | 503 | 507),
                "{c}"
            );
        }
        assert_eq!(ErrorCode::ALL.len(), 40);
        assert!(ErrorCode::NotReady.retry_after() && ErrorCode::NotReady.hides_message());
        assert!(ErrorCode::Internal.hides_message() && !ErrorCode::Internal.retry_after());
        assert!(!ErrorCode::QueueFull.hides_message());
        assert_eq!(ErrorCode::InconsistentParameter.status(), 422);
    }
}
