//! The use-case layer's one error type. Every variant is a kind of failure a front end must
//! tell apart (the API maps each to a status and code in one exhaustive match); messages name
//! the offending input and are meant for the client, except [`AppError::Internal`] and
//! [`AppError::Unavailable`], whose causes are for logs.

use crate::store::StoreError;

/// Result alias of the use-case layer.
pub type AppResult<T> = Result<T, AppError>;

/// Why a use case failed.
#[derive(Debug, thiserror::Error)]
pub enum AppError {
    /// No such map.
    #[error("map {0:016x} does not exist")]
    MapNotFound(u64),
    /// No such localization.
    #[error("localization {0:016x} does not exist")]
    LocalizationNotFound(u64),
    /// No such trip.
    #[error("trip {0:016x} does not exist")]
    TripNotFound(u64),
    /// Frames posted to a closed trip.
    #[error("trip {0:016x} is closed")]
    TripClosed(u64),
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
    #[error("map {0:016x} has no reference images yet")]
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
    /// The map cannot hold more images.
    #[error("map {0:016x} cannot hold more images")]
    MapFull(u64),
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
    /// The store cannot be reached now; retrying later may succeed.
    #[error("the store is unavailable: {0}")]
    Unavailable(String),
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

impl From<StoreError> for AppError {
    fn from(e: StoreError) -> Self {
        match e {
            StoreError::MapNotFound(id) => AppError::MapNotFound(id),
            StoreError::LocalizationNotFound(id) => AppError::LocalizationNotFound(id),
            StoreError::TripNotFound(id) => AppError::TripNotFound(id),
            StoreError::TripClosed(id) => AppError::TripClosed(id),
            StoreError::MapFull(id) => AppError::MapFull(id),
            StoreError::DimensionMismatch { .. } => AppError::DescriptorLength(e.to_string()),
            StoreError::Conflict(_) | StoreError::IdempotencyKeyTaken { .. } => {
                AppError::MapChanged(e.to_string())
            }
            StoreError::TripConflict { .. } => AppError::TripConflict(e.to_string()),
            StoreError::Unavailable(cause) => AppError::Unavailable(cause),
            StoreError::Open { .. }
            | StoreError::IdTaken(_)
            | StoreError::Backend(_)
            | StoreError::Corrupt { .. }
            | StoreError::UnsupportedSchema { .. } => AppError::Internal(e.to_string()),
        }
    }
}
