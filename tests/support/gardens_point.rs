//! The Gardens Point dev data (`gardenspoint_dev`) for the test binaries that run
//! on it: where it is, and a traversal's frames in walking order. One copy, included with
//! `#[path]`, so every binary looks in the same places and skips with the same message.

use std::path::{Path, PathBuf};

/// The Gardens Point dev folder where the tests find it (`seasonloc_test_support::datasets`),
/// or `None` after a `SKIPPED:` line.
pub fn gardens_point() -> Option<PathBuf> {
    seasonloc_test_support::datasets::gardens_point()
}

/// The JPEG frames of one traversal (`day_right`, `day_left`, `night_right`), sorted by name
/// (= walking order).
pub fn traversal(dir: &Path, name: &str) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir.join(name))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "jpg"))
        .collect();
    files.sort();
    files
}
