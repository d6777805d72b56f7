//! The Nordland dev data (`shared/data/nordland_64x32`) for the test binaries that run on it:
//! where it is, and its frames in route order. One copy, included with `#[path]` by each binary,
//! so they all look in the same places and skip with the same message when it is absent.

use std::path::{Path, PathBuf};

/// `../shared/data/nordland_64x32` beside the repository (as in CI), or `../../shared/...`
/// (a git worktree one level further down), if present.
pub fn nordland() -> Option<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for shared in ["../shared", "../../shared"] {
        let dir = root.join(shared).join("data/nordland_64x32");
        if dir.join("summer").is_dir() && dir.join("winter").is_dir() {
            return Some(dir);
        }
    }
    eprintln!(
        "SKIPPED: Nordland data not found at {} (CI clones shared/ beside the repo)",
        root.join("../shared/data/nordland_64x32").display()
    );
    None
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
