//! Wire types of the operations routes.

use serde::Serialize;

/// Health answer.
#[derive(Clone, Debug, Serialize)]
pub struct StatusResponse {
    /// `ok` or `ready`.
    pub status: &'static str,
}
