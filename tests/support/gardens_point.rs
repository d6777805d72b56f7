//! The Gardens Point dev data (`shared/data/gardenspoint_dev`) for the test binaries that run
//! on it: where it is, and a traversal's frames in walking order. One copy, included with
//! `#[path]`, so every binary looks in the same places and skips with the same message.

use std::path::{Path, PathBuf};

/// `../shared/data/gardenspoint_dev` beside the repository (as in CI), or `../../shared/...`
/// (a git worktree one level further down), if present.
pub fn gardens_point() -> Option<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for shared in ["../shared", "../../shared"] {
        let dir = root.join(shared).join("data/gardenspoint_dev");
        if ["day_right", "day_left", "night_right"]
            .iter()
            .all(|t| dir.join(t).is_dir())
        {
            return Some(dir);
        }
    }
    eprintln!(
        "SKIPPED: Gardens Point data not found at {} (CI clones shared/ beside the repo)",
        root.join("../shared/data/gardenspoint_dev").display()
    );
    None
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
