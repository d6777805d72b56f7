//! The HTTP edge of the service (axum): routes of `spec.md` §6, JSON wire types, the error type
//! that maps every failure to a status and `{"error": {"code", "message"}}`, limits, metrics.
//!
//! Only this module knows axum and JSON. Handlers parse and validate input, run CPU work on the
//! rayon pool and store I/O on blocking threads ([`state`]), and convert store and core types
//! to wire types ([`dto`]) at the edge. One file per resource: [`maps`](self) (maps and their
//! reference images), `localize` (localizations), [`trips`] (online trips), `ops` (health, metrics, OpenAPI),
//! `dashboard` (the embedded web dashboard for people).

mod cooc;
mod dashboard;
pub mod dto;
pub mod error;
pub mod extract;
mod localize;
mod maps;
pub mod metrics;
pub mod ops;
mod router;
pub mod state;
pub mod trips;
pub mod upload;

pub use error::ApiError;
pub use router::{app, ROUTES};
pub use state::AppState;
