//! End-to-end tests of the `seasonloc` command line, one module per concern: `solve` on
//! generated `.npy` matrices (`solve.rs`), `eval` on generated image routes (`eval.rs`), the
//! co-occurrence methods through `eval` (`cooc.rs`), and the acceptance numbers on the shared
//! Nordland and Gardens Point data (`acceptance.rs`, skipped with a message when
//! `../shared/data` is absent). Helpers (temporary folders, the binary, `.npy` and image
//! writers) are in `common.rs`.

mod acceptance;
mod common;
mod cooc;
mod eval;
mod solve;
