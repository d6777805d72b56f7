//! The HTTP edge of the service (axum): routes of `spec.md` §6, JSON wire types, the error type
//! that maps every failure to a status and `{"error": {"code", "message"}}`, limits, metrics.
//!
//! Only this module knows axum and the JSON wire types. Handlers decode and validate the
//! request, call one use case of [`seasonloc_app::App`] (which runs CPU work on its pool and owns
//! every store access), and convert its answer to wire types at the edge.
//!
//! Layout (one convention for every resource; `tests/layering/main.rs` keeps it acyclic):
//! * a resource is a directory: `<resource>/mod.rs` has its routes and handlers,
//!   `<resource>/dto.rs` its wire types and their conversions. The resources are `maps` (maps
//!   and their reference images), `views` (image pages, thumbnails, pictures), `cooc` (drives
//!   and the co-occurrence method), `localize` (localizations), `trips` (online trips), `ops`
//!   (health, metrics, OpenAPI) and `dashboard` (the embedded web dashboard for people);
//! * the files directly in `api/` are the machinery the resources share ([`error`],
//!   [`extract`], [`upload`], [`idempotency`], [`wire`] ids and page sizes, [`state`], [`body`],
//!   [`admission`], [`auth`], [`metrics`], [`access_log`]); they never import a resource;
//! * `router` composes the resources and the middleware; nothing imports it but this file.

// Request paths must not panic: no `unwrap` outside tests (clippy.toml allows it there), and a
// new enum variant must be handled explicitly rather than fall into `_` (CI denies warnings).
#![warn(clippy::unwrap_used, clippy::wildcard_enum_match_arm)]

// Shared edge machinery: used by the resources, never using them.
pub mod access_log;
pub mod admission;
pub mod auth;
pub mod body;
pub mod error;
pub mod extract;
pub mod idempotency;
pub mod metrics;
pub mod state;
pub mod upload;
pub mod wire;

// Resources: `<resource>/mod.rs` holds the routes and handlers, `<resource>/dto.rs` the wire
// types (when it has any).
mod cooc;
mod dashboard;
mod localize;
mod maps;
mod ops;
mod trips;
mod views;

// Composes the resources and the middleware into the service.
mod router;

pub use error::ApiError;
/// The wire form of a stored localization (what `GET /v1/localizations/{id}` answers).
pub use localize::dto::LocalizationResponse;
pub use router::{app, ROUTES};
pub use state::AppState;
