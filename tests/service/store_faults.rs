//! The real binary on a damaged or full embedded store (issue 42, defects 4 and 5): `serve`
//! refuses a truncated or rolled-back store with a non-zero exit and a line naming the damage
//! (never a panic, never serving with data missing); on a full disk (a 32 MiB tmpfs, root
//! only) writes answer 507 `storage_full`, reads 200, and writes succeed again once space is
//! freed, without a restart. (Both are faults of the embedded engine's own files; the
//! PostgreSQL engine's are the database's, see `service_pg` and `crates/store`'s hung-database
//! test.)

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::json;

use crate::common::{create_vector_map, Process};

/// A store with a few hundred KiB of acknowledged descriptors; the server is stopped after.
fn filled_store(data: &std::path::Path, log: &std::path::Path) {
    let p = Process::serve(data, log);
    let map = create_vector_map(&p.client, "v", 64);
    for b in 0..40 {
        let rows: Vec<Vec<f32>> = (0..16)
            .map(|i| (0..64).map(|k| (b * 16 + i + k) as f32).collect())
            .collect();
        let r = p.client.post_json(
            &format!("/v1/maps/{map}/descriptors"),
            &json!({ "descriptors": rows }),
        );
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    }
    assert!(p.terminate(), "serve did not exit cleanly on SIGTERM");
}

/// Runs `serve` on `data` and waits (at most 30 s) for it to exit; its exit status and stderr.
fn serve_until_exit(data: &std::path::Path) -> (Option<i32>, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_seasonloc"))
        .args(["serve", "--addr", "127.0.0.1:0", "--data-dir"])
        .arg(data)
        .env_remove("SEASONLOC_DATA_DIR")
        .env_remove("SEASONLOC_ADDR")
        .env("RUST_LOG", "info")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            let out = child.wait_with_output().unwrap();
            return (
                status.code(),
                String::from_utf8_lossy(&out.stderr).into_owned(),
            );
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let out = child.wait_with_output().unwrap();
            panic!(
                "serve on a damaged store neither exited nor was refused within 30 s:\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn serve_refuses_a_truncated_store_with_a_clear_message_and_no_panic() {
    let tmp = tempfile::tempdir().unwrap();
    let gold = tmp.path().join("gold");
    filled_store(&gold, &tmp.path().join("gold.log"));
    let db = gold.join("db");
    let size = std::fs::metadata(&db).unwrap().len();
    for (what, frac) in [("1/4", 0.25), ("1/2", 0.5), ("3/4", 0.75)] {
        let data = tmp.path().join(format!("t{frac}"));
        let cp = Command::new("cp")
            .arg("-a")
            .arg(&gold)
            .arg(&data)
            .status()
            .unwrap();
        assert!(cp.success());
        let f = std::fs::OpenOptions::new()
            .write(true)
            .open(data.join("db"))
            .unwrap();
        f.set_len((size as f64 * frac) as u64).unwrap();
        drop(f);
        let (code, text) = serve_until_exit(&data);
        assert!(
            !text.contains("panicked") && !text.contains("stack backtrace"),
            "truncated to {what}: a panic:\n{text}"
        );
        assert_ne!(code, Some(0), "truncated to {what}: exit 0:\n{text}");
        let last: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
        let tail = last[last.len().saturating_sub(3)..].join("\n");
        assert!(
            tail.contains("damaged") && tail.contains("docs/operations.md"),
            "truncated to {what}: the last lines do not name the damage:\n{text}"
        );
    }
    // The untouched store starts.
    let p = Process::serve(&gold, &tmp.path().join("again.log"));
    assert_eq!(p.client.get("/readyz").status, 200);
}

#[test]
fn a_full_disk_answers_507_keeps_reads_and_recovers_without_a_restart() {
    let Some(fs) = seasonloc_test_support::tmpfs::Tmpfs::mount("full disk (serve)", 32) else {
        return;
    };
    let data = fs.path().join("data");
    let tmp = tempfile::tempdir().unwrap();
    let mut p = Process::serve(&data, &tmp.path().join("serve.log"));
    let c = &p.client;
    let map = create_vector_map(c, "full", 256);
    let batch = |base: usize| {
        let rows: Vec<Vec<f32>> = (0..32)
            .map(|i| (0..256).map(|k| (base + i * 256 + k) as f32).collect())
            .collect();
        json!({ "descriptors": rows })
    };
    let url = format!("/v1/maps/{map}/descriptors");
    assert_eq!(c.post_json(&url, &batch(0)).status, 200);
    let filler = fs.fill("filler");
    let mut refused = Vec::new();
    for k in 1..200 {
        let r = c.post_json(&url, &batch(k));
        if r.status != 200 {
            refused.push((r.status, r.json()["error"]["code"].clone()));
            if refused.len() >= 3 {
                break;
            }
        }
    }
    assert!(
        !refused.is_empty(),
        "every batch was acknowledged on a full disk"
    );
    for (status, code) in &refused {
        assert_eq!(
            (*status, code.as_str()),
            (507, Some("storage_full")),
            "{refused:?}"
        );
    }
    assert_eq!(c.get("/v1/maps").status, 200, "a read on a full disk");
    std::fs::remove_file(filler).unwrap();
    let started = Instant::now();
    loop {
        let r = c.post_json(&url, &batch(7));
        if r.status == 200 {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(10),
            "writes still answer {} 10 s after space was freed",
            r.status
        );
        std::thread::sleep(Duration::from_millis(250));
    }
    assert_eq!(c.get("/v1/maps").status, 200);
    assert!(p.alive(), "the server exited");
}
