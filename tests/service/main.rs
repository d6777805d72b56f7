//! Integration tests of `seasonloc serve`: the real server on ephemeral ports, driven over HTTP
//! (in-process for most tests; the built binary for restart, SIGKILL, configuration and the
//! Dockerfile's runtime assumptions).

mod auth;
mod browser;
mod cnn;
mod common;
mod contract;
mod cooc;
mod dashboard;
mod docker;
#[path = "../support/dockerfile.rs"]
mod dockerfile;
mod durability;
mod errors;
mod flow;
mod hardening;
mod http;
mod idempotency;
mod operations;
mod outside;
mod ownership;
mod recordings;
mod spec;
mod store_faults;
mod stored;
mod traces;
mod trips;
mod views;
