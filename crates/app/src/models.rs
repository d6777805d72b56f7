//! Where a CNN map's model may come from: only regular files inside the server's model
//! directory (`--model-dir`), under a size cap.
//!
//! A create request names its model (a file name, or a path inside the directory); anything
//! else — a path outside the directory (also through `..` or a symlink), a directory, a FIFO,
//! a device such as `/dev/zero`, `/proc/self/fd/2`, a missing file — gets one and the same
//! message, so a caller learns nothing about the server's other paths. The check only stats
//! the file and runs on a blocking thread, never on the CPU pool: a FIFO can no longer block
//! the pool, and the size cap bounds the memory the model loader may take.
//!
//! The server's own default model (`--cnn-model`) is the operator's choice and is not
//! subject to this rule.
//!
//! The same rule holds at every use ([`ModelPolicy::check_in_use`]): a map's model is read
//! again at each append, localize and trip batch (its content is checked against the identity
//! recorded at creation), so a file replaced later by a FIFO, a link out of the directory or to
//! `/dev/zero`, or a file over the cap is refused before any byte is read (and the loader opens
//! it without blocking and reads only a regular file, `seasonloc_core`'s `cnn::model`).

use std::path::{Component, Path, PathBuf};

use super::error::{AppError, AppResult};

/// The model-file policy: the directory models are read from and their size cap.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ModelPolicy {
    /// The directory; `None`: requests may not name a model (only the default is used).
    pub dir: Option<PathBuf>,
    /// Largest accepted model file in bytes.
    pub max_bytes: u64,
}

impl ModelPolicy {
    /// The real path of the model `requested` names, checked against the policy (blocking:
    /// stats the file, never opens it).
    pub fn resolve(&self, requested: &Path) -> AppResult<PathBuf> {
        let Some(dir) = &self.dir else {
            return Err(AppError::inconsistent(
                "descriptor.model",
                "this server takes no model files from requests (it has no --model-dir); \
                 omit `model` to use its default model",
            ));
        };
        let not_a_model = || {
            AppError::inconsistent(
                "descriptor.model",
                format!(
                    "`{}` is not a model file in the server's model directory",
                    requested.display()
                ),
            )
        };
        let real_dir = std::fs::canonicalize(dir)
            .map_err(|e| AppError::Internal(format!("model directory {}: {e}", dir.display())))?;
        let candidate = if requested.is_absolute() {
            requested.to_path_buf()
        } else {
            if requested
                .components()
                .any(|c| !matches!(c, Component::Normal(_)))
            {
                return Err(not_a_model());
            }
            real_dir.join(requested)
        };
        // `canonicalize` resolves `..` and symlinks, so the prefix test below is on the file
        // the loader would really open.
        let real = std::fs::canonicalize(&candidate).map_err(|_| not_a_model())?;
        if !real.starts_with(&real_dir) {
            return Err(not_a_model());
        }
        let meta = std::fs::metadata(&real).map_err(|_| not_a_model())?;
        if !meta.is_file() {
            return Err(not_a_model());
        }
        if meta.len() > self.max_bytes {
            return Err(AppError::inconsistent(
                "descriptor.model",
                format!(
                    "`{}` is {} bytes, more than the server's model size limit of {} bytes",
                    requested.display(),
                    meta.len(),
                    self.max_bytes
                ),
            ));
        }
        Ok(real)
    }
}

/// What a map's model is checked against at every use: the policy and the server's default
/// model (cheap to clone into a CPU-pool job).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ModelRules {
    /// The model directory and size cap.
    pub policy: ModelPolicy,
    /// The server's own model (`--cnn-model`), the operator's choice.
    pub default: Option<PathBuf>,
}

impl ModelRules {
    /// [`ModelPolicy::check_in_use`] with this server's default model.
    pub fn check_in_use(&self, model: &Path) -> Result<(), String> {
        self.policy.check_in_use(model, self.default.as_deref())
    }
}

impl ModelPolicy {
    /// The rule of [`ModelPolicy::resolve`] applied again when a map's recorded model is about
    /// to be read (blocking: stats only). `default` is the server's own model (`--cnn-model`),
    /// which stays the operator's choice. The error says why the file may not be used.
    pub fn check_in_use(&self, model: &Path, default: Option<&Path>) -> Result<(), String> {
        if default == Some(model) {
            return Ok(());
        }
        match self.resolve(model) {
            Ok(_) => Ok(()),
            Err(AppError::InconsistentParameter { reason, .. }) => Err(reason),
            Err(other) => Err(other.to_string()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn message(e: AppError) -> String {
        let AppError::InconsistentParameter { name, reason } = e else {
            panic!("{e:?}");
        };
        assert_eq!(name, "descriptor.model");
        reason
    }

    #[test]
    fn only_regular_files_inside_the_directory_under_the_cap() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("models");
        std::fs::create_dir(&dir).unwrap();
        std::fs::write(dir.join("net.onnx"), vec![0u8; 100]).unwrap();
        std::fs::write(dir.join("big.onnx"), vec![0u8; 1001]).unwrap();
        std::fs::create_dir(dir.join("sub")).unwrap();
        std::fs::write(root.path().join("outside.onnx"), b"x").unwrap();
        #[cfg(unix)]
        {
            std::os::unix::fs::symlink(root.path().join("outside.onnx"), dir.join("link.onnx"))
                .unwrap();
            std::os::unix::fs::symlink(dir.join("net.onnx"), dir.join("alias.onnx")).unwrap();
            let fifo = dir.join("fifo.onnx");
            let made = std::process::Command::new("mkfifo").arg(&fifo).status();
            if made.is_ok_and(|s| s.success()) {
                let p = ModelPolicy {
                    dir: Some(dir.clone()),
                    max_bytes: 1000,
                };
                // Returns at once: a FIFO is stat-ed, never opened.
                assert!(message(p.resolve(Path::new("fifo.onnx")).unwrap_err())
                    .contains("not a model file"));
            }
        }
        let p = ModelPolicy {
            dir: Some(dir.clone()),
            max_bytes: 1000,
        };
        let real_dir = std::fs::canonicalize(&dir).unwrap();
        assert_eq!(
            p.resolve(Path::new("net.onnx")).unwrap(),
            real_dir.join("net.onnx")
        );
        assert_eq!(
            p.resolve(&dir.join("net.onnx")).unwrap(),
            real_dir.join("net.onnx")
        );
        #[cfg(unix)]
        assert_eq!(
            p.resolve(Path::new("alias.onnx")).unwrap(),
            real_dir.join("net.onnx"),
            "a symlink inside the directory is fine"
        );
        let same = [
            "absent.onnx",
            "sub",
            "../outside.onnx",
            "link.onnx",
            "/dev/zero",
            "/proc/self/fd/2",
            "/etc/passwd",
        ];
        let mut texts = Vec::new();
        for name in same {
            let m = message(p.resolve(Path::new(name)).unwrap_err());
            assert!(
                m.contains("not a model file in the server's model directory"),
                "{name}: {m}"
            );
            texts.push(m.replace(name, "NAME"));
        }
        texts.dedup();
        assert_eq!(texts.len(), 1, "every refusal reads the same: {texts:?}");
        let m = message(p.resolve(Path::new("big.onnx")).unwrap_err());
        assert!(m.contains("1001 bytes") && m.contains("1000"), "{m}");
        let none = ModelPolicy {
            dir: None,
            max_bytes: 1000,
        };
        assert!(message(none.resolve(Path::new("net.onnx")).unwrap_err()).contains("--model-dir"));
    }
}
