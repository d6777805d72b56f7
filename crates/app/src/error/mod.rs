//! The use-case layer's one error type, and the one table of error codes ([`ErrorCode`]).
//! Every variant is a kind of failure a front end must tell apart and says its code once
//! ([`AppError::code`]); what the store reports arrives as [`AppError::Store`] with the
//! store's own code. Messages name the offending input and are meant for the client, except
//! those whose code hides them ([`ErrorCode::hides_message`]: internal errors and an
//! unreachable store), whose causes are for logs.

mod code;

pub use code::ErrorCode;

use crate::store::StoreError;

/// Result alias of the use-case layer.
pub type AppResult<T> = Result<T, AppError>;

/// Why a use case failed.
#[derive(Debug, thiserror::Error)]
pub enum AppError {
    /// What the store reported (an unknown id, a closed trip, a concurrent write, an
    /// unreachable or broken engine), with the store's code.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The trip changed while a batch was computed, more often than the retries allow.
    #[error("{0}")]
    TripConflict(String),
    /// An unknown, missing or out-of-range parameter.
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter {
        /// The parameter, e.g. `fan_out` or `descriptor.layer`.
        name: String,
        /// Why it was rejected.
        reason: String,
    },
    /// A parameter valid on its own that does not fit the request's other parameters, the
    /// server's limits or the model it names (rules a schema of single fields cannot state).
    #[error("invalid parameter `{name}`: {reason}")]
    InconsistentParameter {
        /// The parameter, e.g. `relocalization_cost` or `descriptor.layer`.
        name: String,
        /// What it does not fit, and why.
        reason: String,
    },
    /// Nothing to work on (no frames, no queries).
    #[error("empty batch: {0}")]
    EmptyBatch(String),
    /// A map without reference images.
    #[error("map `{0:016x}` has no reference images yet")]
    MapEmpty(u64),
    /// A CNN map's model file is no longer the model the map was created with.
    #[error("{0}")]
    ModelMismatch(String),
    /// The use case does not apply to this kind of map.
    #[error("{0}")]
    MapKind(String),
    /// A concurrent request changed the map first; retrying is safe.
    #[error("{0}")]
    MapChanged(String),
    /// An image over the configured pixel limit.
    #[error(
        "{part} is {width}x{height} = {pixels} pixels, more than the configured limit of {limit}"
    )]
    ImageTooLarge {
        /// The part, e.g. `image[2] ("a.png")`.
        part: String,
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// `width * height`.
        pixels: u64,
        /// The configured limit.
        limit: u64,
    },
    /// A batch held decoded as a whole (a co-occurrence map's drive) over the budget of
    /// decoded pixels.
    #[error(
        "the {images} images of this batch would decode to {pixels} pixels, more than the \
         configured budget of {limit} decoded pixels per batch (send fewer or smaller images)"
    )]
    BatchPixels {
        /// Images in the batch.
        images: usize,
        /// The sum of their sizes.
        pixels: u64,
        /// The configured budget.
        limit: u64,
    },
    /// An image that is not a decodable JPEG/PNG.
    #[error("{part}: {reason}")]
    InvalidImage {
        /// The part.
        part: String,
        /// What is wrong with it.
        reason: String,
    },
    /// Descriptors (or images giving them) that do not fit the map.
    #[error("{0}")]
    DescriptorLength(String),
    /// NaN or infinity in the input.
    #[error("{0}")]
    NonFinite(String),
    /// Inputs whose shapes do not fit together.
    #[error("{0}")]
    ShapeMismatch(String),
    /// An `Idempotency-Key` sent again with a different request.
    #[error("{0}")]
    IdempotencyKeyReused(String),
    /// A key that did not open a trip tried to post frames to it or close it.
    #[error("{0}")]
    NotTripOwner(String),
    /// A bug or a broken store: the message is for logs, not for clients.
    #[error("internal error: {0}")]
    Internal(String),
}

impl AppError {
    /// Shorthand for [`AppError::InvalidParameter`].
    pub fn param(name: impl Into<String>, reason: impl Into<String>) -> Self {
        AppError::InvalidParameter {
            name: name.into(),
            reason: reason.into(),
        }
    }

    /// Shorthand for [`AppError::InconsistentParameter`].
    pub fn inconsistent(name: impl Into<String>, reason: impl Into<String>) -> Self {
        AppError::InconsistentParameter {
            name: name.into(),
            reason: reason.into(),
        }
    }
}

impl From<seasonloc_core::Error> for AppError {
    fn from(e: seasonloc_core::Error) -> Self {
        use seasonloc_core::Error as E;
        match e {
            E::InvalidParameter { name, reason } => AppError::param(name, reason),
            E::Inconsistent { name, reason } => AppError::inconsistent(name, reason),
            E::NonFinite { .. } => AppError::NonFinite(e.to_string()),
            E::Shape(s) => AppError::ShapeMismatch(s),
            E::Empty(s) => AppError::EmptyBatch(s),
            E::Image { name, reason } => AppError::InvalidImage { part: name, reason },
            E::Io { .. } | E::Format { .. } => AppError::Internal(e.to_string()),
        }
    }
}

impl AppError {
    /// The code of this error in the one table.
    pub fn code(&self) -> ErrorCode {
        use ErrorCode as C;
        match self {
            AppError::Store(e) => e.code(),
            AppError::TripConflict(_) => C::TripConflict,
            AppError::InvalidParameter { .. } => C::InvalidParameter,
            AppError::InconsistentParameter { .. } => C::InconsistentParameter,
            AppError::EmptyBatch(_) => C::EmptyBatch,
            AppError::BatchPixels { .. } => C::BatchTooLarge,
            AppError::MapEmpty(_) => C::MapEmpty,
            AppError::ModelMismatch(_) => C::ModelMismatch,
            AppError::MapKind(_) => C::MapKind,
            AppError::MapChanged(_) => C::MapChanged,
            AppError::ImageTooLarge { .. } => C::ImageTooLarge,
            AppError::InvalidImage { .. } => C::InvalidImage,
            AppError::DescriptorLength(_) => C::DescriptorLength,
            AppError::NonFinite(_) => C::NonFinite,
            AppError::ShapeMismatch(_) => C::ShapeMismatch,
            AppError::IdempotencyKeyReused(_) => C::IdempotencyKeyReused,
            AppError::NotTripOwner(_) => C::Forbidden,
            AppError::Internal(_) => C::Internal,
        }
    }
}
