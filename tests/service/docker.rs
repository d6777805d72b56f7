//! The Dockerfile's runtime stage, checked without a Docker engine: non-root user, the store on
//! a volume, the exposed port equal to the listen address, and the HEALTHCHECK command run
//! verbatim (port substituted) against the binary started with the image's environment.

use std::path::Path;

use crate::common::Process;
use crate::dockerfile::runtime_stage;

/// `major.minor` of a version string (`"1.88.0"` -> `(1, 88)`).
fn minor_version(v: &str) -> (u32, u32) {
    let mut parts = v
        .split('.')
        .map(|p| p.parse::<u32>().unwrap_or_else(|_| panic!("{v}")));
    (parts.next().unwrap(), parts.next().unwrap_or(0))
}

#[test]
fn the_build_stage_toolchain_builds_the_locked_dependencies() {
    // The build stage's image (`FROM rust:X.Y-...`), the crate's declared `rust-version`, and
    // the newest `rust-version` in the locked dependency tree must agree: an image older than
    // a dependency's minimum fails `cargo build --locked` (as `rust:1.85` did once `tract`
    // needed 1.91), and a `rust-version` below it promises what no build can keep.
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dockerfile = std::fs::read_to_string(root.join("Dockerfile")).unwrap();
    let image = dockerfile
        .lines()
        .find_map(|l| l.trim().strip_prefix("FROM rust:"))
        .expect("a build stage FROM rust:X.Y-...");
    let toolchain = minor_version(image.split(['-', ' ']).next().unwrap());
    assert!(
        dockerfile
            .lines()
            .filter(|l| l.contains("cargo build"))
            .all(|l| l.contains("--locked") && !l.contains("||")),
        "the image must build the locked tree, with no fallback"
    );
    // The build host's packages only: those are the ones a build has downloaded (a fresh
    // machine has no copy of other platforms' crates, and tests run offline).
    let rustc = std::env::var("RUSTC").unwrap_or_else(|_| "rustc".into());
    let version = std::process::Command::new(rustc)
        .arg("-vV")
        .output()
        .unwrap();
    let version = String::from_utf8_lossy(&version.stdout);
    let host = version
        .lines()
        .find_map(|l| l.strip_prefix("host: "))
        .expect("`rustc -vV` names the host");
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = std::process::Command::new(cargo)
        .args(["metadata", "--format-version", "1", "--locked", "--offline"])
        .args(["--filter-platform", host])
        .current_dir(root)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let meta: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let ours = meta["packages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "seasonloc")
        .and_then(|p| p["rust_version"].as_str())
        .expect("Cargo.toml declares a rust-version");
    assert_eq!(
        minor_version(ours),
        toolchain,
        "Cargo.toml rust-version and the Dockerfile's build image differ"
    );
    let newest = meta["packages"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|p| {
            Some((
                minor_version(p["rust_version"].as_str()?),
                p["name"].as_str()?,
            ))
        })
        .max()
        .expect("some package declares a rust-version");
    assert!(
        newest.0 <= toolchain,
        "{} needs Rust {}.{}; the Docker build uses {}.{}",
        newest.1,
        newest.0 .0,
        newest.0 .1,
        toolchain.0,
        toolchain.1
    );
}

#[test]
fn runtime_stage_is_small_non_root_and_consistent() {
    let rt = runtime_stage();
    assert!(rt.stages >= 2, "multi-stage build expected");
    assert!(rt.user != "root" && rt.user != "0", "runs as root");
    let addr = &rt.env["SEASONLOC_ADDR"];
    let port = addr.rsplit(':').next().unwrap();
    assert!(
        addr.starts_with("0.0.0.0:"),
        "must listen on all interfaces in a container: {addr}"
    );
    assert_eq!(rt.expose, vec![port.to_string()]);
    assert_eq!(rt.volumes, vec![rt.env["SEASONLOC_DATA_DIR"].clone()]);
    assert_eq!(rt.entrypoint, vec!["seasonloc"]);
    assert_eq!(rt.cmd, vec!["serve"]);
    assert!(
        rt.env
            .get("SEASONLOC_API_KEYS")
            .is_some_and(|p| p.starts_with("/run/secrets/")),
        "the image reads its API keys from a mounted secret"
    );
    assert!(rt.healthcheck.join(" ").contains("/healthz"));
    let ignore =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join(".dockerignore"))
            .unwrap();
    assert!(
        ignore.lines().any(|l| l.trim() == "target/"),
        "target/ must not be sent to the build"
    );
}

#[test]
fn healthcheck_command_passes_against_the_image_environment() {
    if std::process::Command::new("bash")
        .arg("--version")
        .output()
        .is_err()
    {
        eprintln!("SKIPPED: bash not found (the runtime image has it)");
        return;
    }
    let rt = runtime_stage();
    let tmp = tempfile::tempdir().unwrap();
    // Same environment as the image, except a free port and a temporary volume.
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let image_port = rt.env["SEASONLOC_ADDR"]
        .rsplit(':')
        .next()
        .unwrap()
        .to_string();
    let addr = rt.env["SEASONLOC_ADDR"].replace(&format!(":{image_port}"), &format!(":{port}"));
    let data = tmp.path().join("data");
    let data_s = data.to_string_lossy().into_owned();
    // The image's key file is a mounted secret; stand in a temporary one at another path.
    let keys = tmp.path().join("keys.json");
    std::fs::write(
        &keys,
        r#"{"keys": [{"name": "ops", "role": "admin", "sha256": "2c26b46b68ffc68ff99b453c1d30413413422d706483bfa0f98a5e886266e7ae"}]}"#,
    )
    .unwrap();
    let keys_s = keys.to_string_lossy().into_owned();
    let replaced = ["SEASONLOC_ADDR", "SEASONLOC_DATA_DIR", "SEASONLOC_API_KEYS"];
    let mut env: Vec<(&str, &str)> = rt
        .env
        .iter()
        .filter(|(k, _)| !replaced.contains(&k.as_str()))
        .map(|(k, v)| (k.as_str(), v.as_str()))
        .collect();
    env.push(("SEASONLOC_ADDR", &addr));
    env.push(("SEASONLOC_DATA_DIR", &data_s));
    if rt.env.contains_key("SEASONLOC_API_KEYS") {
        env.push(("SEASONLOC_API_KEYS", &keys_s));
    }
    let args: Vec<&str> = rt.cmd[1..].iter().map(String::as_str).collect();
    let p = Process::start(&args, &env, &tmp.path().join("log"));
    let cmd: Vec<String> = rt
        .healthcheck
        .iter()
        .map(|a| a.replace(&format!("/{image_port}"), &format!("/{port}")))
        .collect();
    let status = std::process::Command::new(&cmd[0])
        .args(&cmd[1..])
        .status()
        .unwrap();
    assert!(status.success(), "HEALTHCHECK failed: {cmd:?}");
    assert!(p.terminate());
    // And it fails when nothing listens.
    let status = std::process::Command::new(&cmd[0])
        .args(&cmd[1..])
        .status()
        .unwrap();
    assert!(!status.success(), "HEALTHCHECK passes with the server down");
    assert!(data.is_dir());
}
