//! The real binary: a restart keeps everything acknowledged; SIGKILL during a stream of uploads
//! leaves every acknowledged batch complete and no batch half-written; SIGTERM exits cleanly;
//! flags and environment variables configure it.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

use serde_json::json;

use crate::common::{create_hog_map, create_vector_map, Process, Route};
use crate::http::Part;

#[test]
fn restart_keeps_everything_acknowledged() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let log = tmp.path().join("serve.log");
    let route = Route::new(24, 11);

    let p = Process::serve(&data, &log);
    let c = p.client;
    let map = create_hog_map(&c, "restart", 8);
    let parts: Vec<Part> = (0..24)
        .map(|i| Part::image(&format!("{i}.png"), route.reference_png(i)))
        .collect();
    let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &parts);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let vectors = create_vector_map(&c, "vectors", 2);
    let r = c.post_json(
        &format!("/v1/maps/{vectors}/descriptors"),
        &json!({"descriptors": [[1, 2], [3, 4]]}),
    );
    assert_eq!(r.status, 200);
    let queries: Vec<Part> = (4..12)
        .map(|i| Part::image(&format!("q{i}.png"), route.query_png(i)))
        .collect();
    let loc = c.post_multipart(&format!("/v1/maps/{map}/localize"), &queries);
    assert_eq!(loc.status, 200, "{}", String::from_utf8_lossy(&loc.body));
    let loc = loc.json();
    let before_maps = c.get("/v1/maps").json();
    assert!(
        p.terminate(),
        "seasonloc serve did not exit cleanly on SIGTERM"
    );
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(text.contains("store flushed"), "{text}");

    let p = Process::serve(&data, &log);
    let c = p.client;
    assert_eq!(c.get("/v1/maps").json(), before_maps);
    let id = loc["id"].as_str().unwrap();
    assert_eq!(c.get(&format!("/v1/localizations/{id}")).json(), loc);
    // New ids keep increasing after a restart, so listings stay newest first.
    let again = c
        .post_multipart(&format!("/v1/maps/{map}/localize"), &queries)
        .json();
    assert!(again["id"].as_str().unwrap() > id);
    let list = c.get(&format!("/v1/localizations?map={map}")).json();
    assert_eq!(list["items"][0]["id"], again["id"]);
    assert_eq!(list["items"][1]["id"], loc["id"]);
    assert!(p.terminate());
}

/// Row `k` of batch `b` (of `n` rows) encodes all three, so a half-written batch is visible.
fn row(b: usize, k: usize, n: usize) -> Vec<f32> {
    vec![b as f32 + 1.0, k as f32, n as f32, 1.0]
}

#[test]
fn sigkill_during_uploads_loses_no_acknowledged_batch() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let log = tmp.path().join("serve.log");
    let p = Process::serve(&data, &log);
    let c = p.client;
    let map = create_vector_map(&c, "stream", 4);
    let acked: Mutex<Vec<(usize, usize)>> = Mutex::new(Vec::new());
    let stop = AtomicBool::new(false);
    std::thread::scope(|s| {
        for client in 0..3usize {
            let (acked, stop, map) = (&acked, &stop, &map);
            s.spawn(move || {
                let mut b = client;
                while !stop.load(Ordering::SeqCst) {
                    let n = 1 + (b * 7) % 13;
                    let rows: Vec<Vec<f32>> = (0..n).map(|k| row(b, k, n)).collect();
                    let body = serde_json::to_vec(&json!({"descriptors": rows})).unwrap();
                    match c.try_request(
                        "POST",
                        &format!("/v1/maps/{map}/descriptors"),
                        Some("application/json"),
                        &body,
                    ) {
                        Ok(r) if r.status == 200 => acked.lock().unwrap().push((b, n)),
                        Ok(r) => panic!("upload failed: {}", String::from_utf8_lossy(&r.body)),
                        Err(_) => break, // the server was killed mid-request
                    }
                    b += 3;
                }
            });
        }
        std::thread::sleep(std::time::Duration::from_millis(1500));
        p.kill();
        stop.store(true, Ordering::SeqCst);
    });
    let acked = acked.into_inner().unwrap();
    assert!(
        acked.len() >= 3,
        "too few uploads before the kill: {}",
        acked.len()
    );

    // Restart the binary: it comes up on the same folder and reports at least every acked row.
    let p = Process::serve(&data, &log);
    let count = p.client.get(&format!("/v1/maps/{map}")).json()["image_count"]
        .as_u64()
        .unwrap() as usize;
    let acked_rows: usize = acked.iter().map(|(_, n)| n).sum();
    assert!(
        count >= acked_rows,
        "{count} rows stored, {acked_rows} acknowledged"
    );
    assert!(p.terminate());

    // Inspect the store: rows form whole batches, and every acknowledged batch is there.
    let store = seasonloc_store::SledStore::open(&data).unwrap();
    let id = u64::from_str_radix(&map, 16).unwrap();
    let (_, m) = store.references(id).unwrap();
    let mut seen = std::collections::HashMap::new();
    let mut i = 0;
    while i < m.rows() {
        let (b, n) = (m.get(i, 0) as usize - 1, m.get(i, 2) as usize);
        for k in 0..n {
            assert!(i + k < m.rows(), "batch {b} is cut off at the end");
            assert_eq!(
                m.row(i + k),
                row(b, k, n).as_slice(),
                "batch {b} is half-written"
            );
        }
        seen.insert(b, n);
        i += n;
    }
    for (b, n) in acked {
        assert_eq!(seen.get(&b), Some(&n), "acknowledged batch {b} is missing");
    }
}

#[test]
fn environment_configures_and_flags_win() {
    let tmp = tempfile::tempdir().unwrap();
    let env_dir = tmp.path().join("from-env");
    let flag_dir = tmp.path().join("from-flag");
    let log = tmp.path().join("serve.log");
    let env_dir_s = env_dir.to_string_lossy().into_owned();
    let p = Process::start(
        &[],
        &[
            ("SEASONLOC_ADDR", "127.0.0.1:0"),
            ("SEASONLOC_DATA_DIR", &env_dir_s),
        ],
        &log,
    );
    assert_eq!(p.client.get("/healthz").status, 200);
    assert!(p.terminate());
    assert!(env_dir.is_dir(), "SEASONLOC_DATA_DIR was not used");
    let flag = flag_dir.to_string_lossy().into_owned();
    let p = Process::start(
        &["--data-dir", &flag],
        &[
            ("SEASONLOC_ADDR", "127.0.0.1:0"),
            ("SEASONLOC_DATA_DIR", &env_dir_s),
        ],
        &log,
    );
    assert!(p.terminate());
    assert!(
        flag_dir.is_dir(),
        "--data-dir did not win over SEASONLOC_DATA_DIR"
    );
    // Exactly one line announces the address.
    let text = std::fs::read_to_string(&log).unwrap();
    assert_eq!(text.matches("listening on http://").count(), 1, "{text}");
}

#[test]
fn bad_configuration_exits_with_a_reason() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_seasonloc"))
        .args(["serve", "--addr", "127.0.0.1:0", "--localize-queue", "0"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("localize_queue"), "{err}");
}

#[test]
fn sigterm_lets_in_flight_requests_finish() {
    use std::io::{Read, Write};
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let log = tmp.path().join("serve.log");
    let mut p = Process::serve(&data, &log);
    let map = create_vector_map(&p.client, "drain", 2);
    let body = serde_json::to_vec(&json!({"descriptors": [[1, 2], [3, 4]]})).unwrap();
    let mut s = std::net::TcpStream::connect(p.client.addr).unwrap();
    let head = format!(
        "POST /v1/maps/{map}/descriptors HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\
         Content-Type: application/json\r\nContent-Length: {}\r\n\r\n",
        body.len()
    );
    s.write_all(head.as_bytes()).unwrap();
    s.write_all(&body[..5]).unwrap();
    std::thread::sleep(std::time::Duration::from_millis(300));
    // SIGTERM while the request is half-sent: the server must wait for it.
    let pid = p.child.id().to_string();
    let kill = std::process::Command::new("sh")
        .args(["-c", &format!("kill -TERM {pid}")])
        .status()
        .unwrap();
    assert!(kill.success());
    std::thread::sleep(std::time::Duration::from_millis(300));
    s.write_all(&body[5..]).unwrap();
    let mut answer = String::new();
    s.read_to_string(&mut answer).unwrap();
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
    assert!(p.child.wait().unwrap().success());
    let p = Process::serve(&data, &log);
    let m = p.client.get(&format!("/v1/maps/{map}")).json();
    assert_eq!(m["image_count"], 2);
    assert!(p.terminate());
}
