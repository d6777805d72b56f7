//! The seasonloc HTTP service: [`api`] (axum routes, wire types, errors, limits, the
//! dashboard), [`config`] (the `serve` flags and their environment variables), [`config_file`] (the
//! same as a TOML file), [`connections`]
//! (the connection cap) and [`service`] (start-up on the chosen store engine, graceful
//! shutdown). The only crate that knows axum.
#![warn(missing_docs)]

pub mod api;
pub mod config;
pub mod config_file;
pub mod connections;
pub mod service;
pub mod telemetry;
