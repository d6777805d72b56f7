//! The service's integration tests again, with every in-process server on PostgreSQL (a real
//! server started by `seasonloc_test_support::postgres`, one database per server), plus the
//! tests only a shared database has: several replicas on one database, and faults of the
//! database under a replica ([`replicas`]), and a replica started from the Kubernetes manifests
//! ([`deploy`]).
//!
//! The test files are `tests/service/*.rs`, compiled a second time (not copied): the harness
//! (`common::on_postgres`) picks the engine from this binary's name. Tests of the embedded
//! store's own folder (restart, SIGKILL), the Dockerfile and the browser stay in `service`
//! only (the tests of `trips` that restart a process run on the embedded store in both).
//!
//! Needs PostgreSQL's server binaries (Debian `postgresql`); without them each test says so and
//! is skipped, except under `CI=true`, where it fails.

// Helpers used only by the tests left out of this binary.
#![allow(dead_code)]

#[path = "../service/auth.rs"]
mod auth;
#[path = "../service/cnn.rs"]
mod cnn;
#[path = "../service/common.rs"]
mod common;
#[path = "../service/contract.rs"]
mod contract;
#[path = "../service/cooc.rs"]
mod cooc;
mod deploy;
#[path = "../support/dockerfile.rs"]
mod dockerfile;
#[path = "../service/errors.rs"]
mod errors;
#[path = "../service/flow.rs"]
mod flow;
#[path = "../service/hardening.rs"]
mod hardening;
#[path = "../service/http.rs"]
mod http;
#[path = "../service/idempotency.rs"]
mod idempotency;
#[path = "../service/operations.rs"]
mod operations;
#[path = "../service/outside.rs"]
mod outside;
mod replicas;
#[path = "../service/spec.rs"]
mod spec;
#[path = "../service/trips.rs"]
mod trips;
#[path = "../service/views.rs"]
mod views;
