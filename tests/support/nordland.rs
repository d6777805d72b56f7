//! The Nordland dev data (`nordland_64x32`) for the test binaries that run on it:
//! where it is, and its frames in route order. One copy, included with `#[path]` by each binary,
//! so they all look in the same places and skip with the same message when it is absent.

use std::path::{Path, PathBuf};

/// The Nordland dev folder where the tests find it (`seasonloc_test_support::datasets`), or
/// `None` after a `SKIPPED:` line.
pub fn nordland() -> Option<PathBuf> {
    seasonloc_test_support::datasets::nordland()
}

/// File names of a Nordland season folder, sorted (= route order).
pub fn nordland_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    files.sort();
    files
}
