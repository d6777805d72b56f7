//! Helpers shared by the workspace's test suites (dev-only, never a dependency of the
//! service): where the public datasets and the CNN model are ([`datasets`]), and throw-away
//! PostgreSQL servers ([`postgres`]), a small tmpfs that fills up ([`tmpfs`]).

pub mod datasets;
pub mod postgres;
pub mod tmpfs;
