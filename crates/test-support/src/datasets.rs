//! Where the public datasets and the CNN model are, for the tests, benches and examples that
//! run on them. One rule for every test binary, so they all look in the same places and skip
//! with the same message when the data is absent.
//!
//! A dataset `NAME` (`nordland_64x32`, `gardenspoint_dev`) is looked for in
//! `$SEASONLOC_DATASETS/NAME`, then in `data/NAME` at the workspace root, then in the folder
//! CI places beside the repository (`shared/data/NAME` one or two levels above the workspace).
//! The model folder likewise: `$SEASONLOC_DATASETS/models`, `data/models`, `shared/models`.

use std::path::{Path, PathBuf};

/// The workspace root (the folder of the top-level `Cargo.toml`).
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn candidates(name: &str, shared_sub: &str) -> Vec<PathBuf> {
    let root = workspace_root();
    let mut out = Vec::new();
    if let Some(dir) = std::env::var_os("SEASONLOC_DATASETS") {
        out.push(PathBuf::from(dir).join(name));
    }
    out.push(root.join("data").join(name));
    for up in ["..", "../.."] {
        out.push(root.join(up).join("shared").join(shared_sub).join(name));
    }
    out
}

/// The folder of dataset `name` when it holds `must_have` (sub-folders or files), else
/// `None` after printing a `SKIPPED:` line that names where it was looked for.
pub fn dataset(name: &str, must_have: &[&str]) -> Option<PathBuf> {
    let places = candidates(name, "data");
    for dir in &places {
        if must_have.iter().all(|m| dir.join(m).exists()) {
            return Some(dir.clone());
        }
    }
    eprintln!(
        "SKIPPED: dataset {name} not found (looked in {}; set SEASONLOC_DATASETS to a folder holding {name}/)",
        places.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ")
    );
    None
}

/// The file `file` of the model folder, when present (no message: callers say what they skip).
pub fn model_file(file: &str) -> Option<PathBuf> {
    let root = workspace_root();
    let mut places = Vec::new();
    if let Some(dir) = std::env::var_os("SEASONLOC_DATASETS") {
        places.push(PathBuf::from(dir).join("models"));
    }
    places.push(root.join("data/models"));
    for up in ["..", "../.."] {
        places.push(root.join(up).join("shared/models"));
    }
    places
        .into_iter()
        .map(|p| p.join(file))
        .find(|p| p.is_file())
}

/// The Nordland dev data (`summer/` and `winter/`), or `None` with a `SKIPPED:` line.
pub fn nordland() -> Option<PathBuf> {
    dataset("nordland_64x32", &["summer", "winter"])
}

/// The Gardens Point dev data (`day_left/`, `day_right/`, `night_right/`), or `None` with a
/// `SKIPPED:` line.
pub fn gardens_point() -> Option<PathBuf> {
    dataset(
        "gardenspoint_dev",
        &["day_left", "day_right", "night_right"],
    )
}

/// The image files (PNG or JPEG) of a folder, sorted by name (= route order).
pub fn image_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.expect("a readable folder entry").path())
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
        })
        .collect();
    files.sort();
    files
}

/// `rel` written as the data's usual layout, `data/<dataset>/...` or `models/...`, resolved
/// where the data is found (see the module doc); `None` after a `SKIPPED:` line when absent.
pub fn resolve(rel: &str) -> Option<PathBuf> {
    let path = match rel.split_once('/') {
        Some(("models", rest)) => {
            model_file("efficientnet-lite0-224.onnx").and_then(|m| m.parent().map(|d| d.join(rest)))
        }
        Some(("data", rest)) => {
            let (name, rest) = rest.split_once('/').unwrap_or((rest, ""));
            candidates(name, "data")
                .into_iter()
                .find(|d| d.is_dir())
                .map(|d| d.join(rest))
        }
        _ => None,
    };
    match path {
        Some(p) if p.exists() => Some(p),
        _ => {
            eprintln!("SKIPPED: {rel} not found (set SEASONLOC_DATASETS to the folder of the public datasets and models/)");
            None
        }
    }
}
