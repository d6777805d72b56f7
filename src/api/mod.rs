//! The HTTP edge of the service (axum): routes of `spec.md` §6, JSON wire types, the error type
//! that maps every failure to a status and `{"error": {"code", "message"}}`, limits, metrics.
//!
//! Only this module knows axum and the JSON wire types. Handlers decode and validate the
//! request, call one use case of [`crate::app::App`] (which runs CPU work on its pool and owns
//! every store access), and convert its answer to wire types ([`dto`]) at the edge. One file
//! per resource plus [`auth`] (API keys and roles): `maps` (maps and their reference images), `cooc` (drives), `localize`
//! (localizations), [`trips`] (online trips), [`ops`] (health, metrics, OpenAPI),
//! `dashboard` (the embedded web dashboard for people).

// Request paths must not panic: no `unwrap` outside tests (clippy.toml allows it there), and a
// new enum variant must be handled explicitly rather than fall into `_` (CI denies warnings).
#![warn(clippy::unwrap_used, clippy::wildcard_enum_match_arm)]

pub mod admission;
pub mod auth;
mod cooc;
mod dashboard;
pub mod dto;
pub mod error;
pub mod extract;
pub mod idempotency;
mod localize;
mod maps;
pub mod metrics;
pub mod ops;
mod router;
pub mod state;
pub mod trips;
pub mod upload;
mod views;

pub use error::ApiError;
pub use router::{app, ROUTES};
pub use state::AppState;
