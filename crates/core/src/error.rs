//! The core layer's one error type.
//!
//! Every algorithm module (features, similarity, solver, baselines, eval) reports failures as
//! [`Error`]. Variants describe *what* was wrong with the input in words a user can act on; the
//! CLI prints them as one line and the API maps them to 4xx/5xx statuses.

use std::path::PathBuf;

/// Result alias for the core layer.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Errors of the core layer.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A parameter is out of its valid range (`name` is the user-facing parameter name).
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter {
        /// The parameter's user-facing name, e.g. `fan_out`.
        name: &'static str,
        /// Why it was rejected.
        reason: String,
    },
    /// A parameter that is valid on its own but does not fit the other parameters of the same
    /// request (e.g. a spatial tolerance at least the grid size), the data it applies to or
    /// the model it names: a rule no schema of single fields can state.
    #[error("invalid parameter `{name}`: {reason}")]
    Inconsistent {
        /// The parameter's user-facing name, e.g. `spatial_tolerance`.
        name: &'static str,
        /// What it does not fit, and why.
        reason: String,
    },
    /// A matrix or vector contains NaN or an infinity.
    #[error("non-finite value ({value}) in {what} at row {row}, column {col}")]
    NonFinite {
        /// Which input, e.g. "similarity matrix".
        what: &'static str,
        /// Row index.
        row: usize,
        /// Column index.
        col: usize,
        /// The offending value.
        value: f64,
    },
    /// Shapes of two inputs do not fit together.
    #[error("shape mismatch: {0}")]
    Shape(String),
    /// An input is empty where at least one element is required.
    #[error("empty input: {0}")]
    Empty(String),
    /// An image could not be decoded or has an unusable size.
    #[error("image {name}: {reason}")]
    Image {
        /// File name or part name of the image.
        name: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The path involved.
        path: PathBuf,
        /// The underlying I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A file's contents are malformed (CSV, NPY, ...).
    #[error("{path}: {reason}")]
    Format {
        /// The path involved.
        path: PathBuf,
        /// What is malformed.
        reason: String,
    },
}

impl Error {
    /// Shorthand for [`Error::InvalidParameter`].
    pub fn param(name: &'static str, reason: impl Into<String>) -> Self {
        Error::InvalidParameter {
            name,
            reason: reason.into(),
        }
    }

    /// Shorthand for [`Error::Inconsistent`].
    pub fn inconsistent(name: &'static str, reason: impl Into<String>) -> Self {
        Error::Inconsistent {
            name,
            reason: reason.into(),
        }
    }
}
