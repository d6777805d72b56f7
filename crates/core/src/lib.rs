//! seasonloc: visual localization on a previously driven route, across seasons.
//!
//! The crate is layered (see `ARCHITECTURE.md`):
//!
//! * **core** — [`features`], [`similarity`], [`solver`], [`baselines`], [`eval`]: pure
//!   algorithms on images, descriptor matrices and similarity matrices. They know nothing of
//!   HTTP, JSON or the store, and report failures as [`Error`].
//! * **cli** — the `seasonloc solve` / `seasonloc eval` front end (`src/cli`).
//! * **app** — the use cases of the service ([`app`]): the only caller of the store, the only
//!   dispatch on a map's kind, CPU work on its own pool.
//! * **store** — the [`store::Store`] trait and its engines (sled, embedded, the default;
//!   PostgreSQL, shared by replicas): only `store` knows a database.
//! * **api** — the HTTP edge ([`api`], [`config`], [`service`]): only `api` knows axum and the
//!   JSON wire types.
//!
//! The method is Naseer, Burgard & Stachniss, *Robust Visual Localization Across Seasons*:
//! global descriptors -> cosine similarity matrix (Eq. 1) -> column normalisation (Eq. 2)
//! -> min-cost flow on a DAG of matching and hidden nodes.
#![warn(missing_docs)]

pub mod baselines;
pub mod codec;
pub mod confidence;
pub mod cooc;
pub mod error;
pub mod eval;
pub mod features;
pub mod localize;
pub mod matrix;
pub mod picture;
pub mod similarity;
pub mod solver;
pub mod trip;
pub mod window;

pub use error::{Error, Result};
pub use matrix::Matrix;
