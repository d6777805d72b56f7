//! Sets `SEASONLOC_BUILD_COMMIT` for `seasonloc_build_info`: the variable of that name at build
//! time when set (a container build without `.git`), else `git rev-parse --short=12 HEAD`,
//! else `unknown`.

fn main() {
    println!("cargo:rerun-if-env-changed=SEASONLOC_BUILD_COMMIT");
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    // A new commit moves the branch HEAD names (not the index: staging must not rebuild).
    let head = root.join(".git/HEAD");
    if head.is_file() {
        println!("cargo:rerun-if-changed={}", head.display());
        if let Some(r) = std::fs::read_to_string(&head)
            .ok()
            .and_then(|t| t.strip_prefix("ref: ").map(|r| r.trim().to_string()))
        {
            for f in [root.join(".git").join(r), root.join(".git/packed-refs")] {
                if f.exists() {
                    println!("cargo:rerun-if-changed={}", f.display());
                }
            }
        }
    }
    let commit = std::env::var("SEASONLOC_BUILD_COMMIT")
        .ok()
        .filter(|c| !c.is_empty())
        .or_else(|| {
            std::process::Command::new("git")
                .args(["rev-parse", "--short=12", "HEAD"])
                .current_dir(&root)
                .output()
                .ok()
                .filter(|o| o.status.success())
                .and_then(|o| String::from_utf8(o.stdout).ok())
                .map(|s| s.trim().to_string())
        })
        .filter(|c| !c.is_empty() && c.bytes().all(|b| b.is_ascii_alphanumeric()))
        .unwrap_or_else(|| "unknown".to_string());
    println!("cargo:rustc-env=SEASONLOC_BUILD_COMMIT={commit}");
}
