//! A small tmpfs for tests that need a disk that fills up (the embedded store on a full disk).
//! Mounting needs root: without it [`Tmpfs::mount`] prints why the test is skipped and returns
//! `None` (under `CI=true`, which runs as root, it panics instead: CI must never pass by
//! skipping). Dropping it unmounts it and removes its folder.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicUsize, Ordering};

/// A mounted tmpfs of a few MiB.
pub struct Tmpfs {
    dir: PathBuf,
}

static NEXT: AtomicUsize = AtomicUsize::new(0);

impl Tmpfs {
    /// Mounts a tmpfs of `mib` MiB in a new temporary folder, for `test`.
    pub fn mount(test: &str, mib: u32) -> Option<Tmpfs> {
        let ci = std::env::var("CI").is_ok_and(|v| v == "true");
        if !crate::postgres::is_root() {
            assert!(
                !ci,
                "{test}: needs root to mount a tmpfs, and CI=true runs as root"
            );
            eprintln!(
                "SKIPPED {test}: needs root to mount a tmpfs (run as root to test a full disk)"
            );
            return None;
        }
        let dir = std::env::temp_dir().join(format!(
            "seasonloc-tmpfs-{}-{}",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir).ok()?;
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o"])
            .arg(format!("size={mib}m,mode=0755"))
            .arg("tmpfs")
            .arg(&dir)
            .output();
        match out {
            Ok(o) if o.status.success() => Some(Tmpfs { dir }),
            other => {
                let why = match other {
                    Ok(o) => String::from_utf8_lossy(&o.stderr).trim().to_string(),
                    Err(e) => e.to_string(),
                };
                let _ = std::fs::remove_dir(&dir);
                assert!(!ci, "{test}: cannot mount a tmpfs under CI=true: {why}");
                eprintln!("SKIPPED {test}: cannot mount a tmpfs: {why}");
                None
            }
        }
    }

    /// The mounted folder.
    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// Fills the tmpfs with the file `name` until no byte more fits; returns its path.
    pub fn fill(&self, name: &str) -> PathBuf {
        use std::io::Write;
        let path = self.dir.join(name);
        let mut f = std::fs::File::create(&path).expect("the filler file");
        for size in [1 << 20, 4096, 64, 1] {
            let block = vec![0u8; size];
            while f.write_all(&block).is_ok() {}
        }
        path
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        for args in [&["umount"][..], &["umount", "-l"][..]] {
            let ok = Command::new(args[0])
                .args(&args[1..])
                .arg(&self.dir)
                .status()
                .is_ok_and(|s| s.success());
            if ok {
                break;
            }
        }
        let _ = std::fs::remove_dir(&self.dir);
    }
}
