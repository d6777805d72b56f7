//! What operators read (issue 45): the JSON access log of the real binary, the configuration
//! file's precedence under the environment and the flags, and the fleet's metrics moving under
//! a short trip (on both store engines: this file is compiled into `service_pg` too).

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use serde_json::{json, Value};
use sha2::{Digest, Sha256};

use crate::common::{create_hog_map, Process, Route, Server};
use crate::http::Part;

const ADMIN_KEY: &str = "k-ops-5b1e9f0c";

fn sha(key: &str) -> String {
    Sha256::digest(key.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The access log lines (target `seasonloc::access`) among the JSON lines of `log`.
fn access_lines(log: &str) -> Vec<Value> {
    log.lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter(|v| v["target"] == "seasonloc::access")
        .collect()
}

#[test]
fn the_json_log_has_one_line_per_request_with_its_fields_and_never_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let keys = dir.path().join("keys.json");
    std::fs::write(
        &keys,
        json!({"keys": [{"name": "ops", "role": "admin", "sha256": sha(ADMIN_KEY)}]}).to_string(),
    )
    .unwrap();
    let log = dir.path().join("log");
    let data = dir.path().join("data");
    let p = Process::start(
        &[
            "--addr",
            "127.0.0.1:0",
            "--data-dir",
            &data.to_string_lossy(),
            "--api-keys",
            &keys.to_string_lossy(),
        ],
        &[("SEASONLOC_LOG_FORMAT", "json")],
        &log,
    );
    let c = &p.client;
    let auth = format!("Bearer {ADMIN_KEY}");
    let h = [
        ("Authorization", auth.as_str()),
        ("x-request-id", "req-ops-1"),
    ];
    let body = json!({"name": "logged", "descriptor": {"kind": "precomputed", "dim": 4}});
    let r = c.request_with(
        "POST",
        "/v1/maps",
        &h,
        Some("application/json"),
        body.to_string().as_bytes(),
    );
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let map = r.json()["id"].as_str().unwrap().to_string();
    let h2 = [
        ("Authorization", auth.as_str()),
        ("x-request-id", "req-ops-2"),
    ];
    let r = c.request_with("GET", &format!("/v1/maps/{map}/trips"), &h2, None, b"");
    assert_eq!(r.status, 200);
    let h3 = [
        ("Authorization", auth.as_str()),
        ("x-request-id", "req-ops-3"),
    ];
    let r = c.request_with("GET", "/v1/trips/ffffffffffffffff", &h3, None, b"");
    assert_eq!(r.status, 404);
    let missing = r.json()["error"]["code"].as_str().unwrap().to_string();
    let r = c.request_with(
        "GET",
        "/v1/maps",
        &[("x-request-id", "req-ops-4")],
        None,
        b"",
    );
    assert_eq!(r.status, 401);

    // The line of a request is written once its response is; wait for the last one.
    let deadline = Instant::now() + Duration::from_secs(10);
    let lines = loop {
        let text = std::fs::read_to_string(&log).unwrap_or_default();
        let lines = access_lines(&text);
        if lines.iter().any(|l| l["request_id"] == "req-ops-4") {
            break lines;
        }
        assert!(
            Instant::now() < deadline,
            "no access line for req-ops-4:\n{text}"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    let by_id: BTreeMap<String, &Value> = lines
        .iter()
        .filter_map(|l| Some((l["request_id"].as_str()?.to_string(), l)))
        .collect();
    let created = by_id["req-ops-1"];
    for field in ["timestamp", "level", "target", "message", "latency_ms"] {
        assert!(!created[field].is_null(), "no `{field}` in {created}");
    }
    assert_eq!(created["level"], "INFO");
    assert_eq!(created["method"], "POST");
    assert_eq!(created["route"], "/v1/maps");
    assert_eq!(created["status"], 201);
    assert_eq!(created["key"], "ops");
    assert!(created["error_code"].is_null(), "{created}");
    assert!(created["latency_ms"].as_f64().unwrap() >= 0.0);
    let listed = by_id["req-ops-2"];
    assert_eq!(listed["route"], "/v1/maps/{id}/trips");
    assert_eq!(listed["map_id"], map.as_str());
    let not_found = by_id["req-ops-3"];
    assert_eq!(not_found["status"], 404);
    assert_eq!(not_found["level"], "WARN");
    assert_eq!(not_found["trip_id"], "ffffffffffffffff");
    assert_eq!(not_found["error_code"], missing.as_str());
    let refused = by_id["req-ops-4"];
    assert_eq!(refused["status"], 401);
    assert_eq!(refused["error_code"], "unauthorized");
    assert!(refused["key"].is_null());
    // Every line of the log is one JSON object (the start-up lines too), and no key leaked.
    let text = std::fs::read_to_string(&log).unwrap();
    for line in text.lines() {
        let v: Value = serde_json::from_str(line).unwrap_or_else(|e| panic!("{e}: {line}"));
        assert!(v.is_object());
    }
    assert!(!text.contains(ADMIN_KEY), "the key leaked into the log");
    assert!(p.terminate());
}

/// Starts `seasonloc serve --config FILE` with `args` and `env` and answers the status of a
/// 2,000-byte POST (413 when the effective `max_body_bytes` is below it).
fn status_of_a_2000_byte_post(dir: &std::path::Path, args: &[&str], env: &[(&str, &str)]) -> u16 {
    let log = dir.join("log");
    let config = dir.join("seasonloc.toml");
    let data = dir.join("data");
    let mut all = vec!["--config", config.to_str().unwrap(), "--data-dir"];
    all.push(data.to_str().unwrap());
    all.extend_from_slice(args);
    let p = Process::start(&all, env, &log);
    let body = vec![b' '; 2000];
    let status = p
        .client
        .request("POST", "/v1/maps", Some("application/json"), &body)
        .status;
    assert!(p.terminate());
    status
}

#[test]
fn the_config_file_sets_what_the_environment_and_the_flags_do_not() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("seasonloc.toml"),
        "addr = \"127.0.0.1:0\"\nmax_body_bytes = 1000\n",
    )
    .unwrap();
    // The file alone: 1,000 bytes.
    assert_eq!(status_of_a_2000_byte_post(dir.path(), &[], &[]), 413);
    // The environment wins over the file: 5,000 bytes (the body is read; it is not JSON).
    let env = [("SEASONLOC_MAX_BODY_BYTES", "5000")];
    assert_eq!(status_of_a_2000_byte_post(dir.path(), &[], &env), 400);
    // The flag wins over both.
    let flag = ["--max-body-bytes", "1500"];
    assert_eq!(status_of_a_2000_byte_post(dir.path(), &flag, &env), 413);
    // SEASONLOC_CONFIG names the file as well as the flag does.
    let log = dir.path().join("log");
    let data = dir.path().join("data");
    let config = dir.path().join("seasonloc.toml");
    let p = Process::start(
        &["--data-dir", data.to_str().unwrap()],
        &[("SEASONLOC_CONFIG", config.to_str().unwrap())],
        &log,
    );
    let r = p
        .client
        .request("POST", "/v1/maps", Some("application/json"), &[b' '; 2000]);
    assert_eq!(r.status, 413);
    assert!(p.terminate());

    // An unknown key stops the service before it starts, naming the key and the file.
    std::fs::write(&config, "addr = \"127.0.0.1:0\"\nmax_body_byte = 10\n").unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_seasonloc"))
        .args(["serve", "--config", config.to_str().unwrap()])
        .env_remove("SEASONLOC_ADDR")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("unknown key `max_body_byte`") && err.contains("seasonloc.toml"),
        "{err}"
    );
    // A value the flag's parser refuses is refused in the file's name.
    std::fs::write(&config, "max_body_bytes = \"lots\"\n").unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_seasonloc"))
        .args(["serve", "--config", config.to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("config file") && err.contains("lots"), "{err}");
}

/// The value of the sample `name` (with its labels exactly as written, e.g.
/// `seasonloc_trips_open{status="new"}`) in an exposition text.
fn sample(text: &str, name: &str) -> Option<f64> {
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.trim().parse().ok())
}

#[test]
fn the_fleet_metrics_move_under_a_short_trip() {
    let server = Server::start();
    let c = &server.client;
    let route = Route::new(40, 7);
    let map = create_hog_map(c, "metrics-route", 8);
    for start in (0..40).step_by(10) {
        let parts: Vec<Part> = (start..start + 10)
            .map(|i| Part::image(&format!("r{i}.png"), route.reference_png(i)))
            .collect();
        let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &parts);
        assert_eq!(r.status, 200);
    }
    let before = String::from_utf8(c.get("/metrics").body).unwrap();
    assert_eq!(sample(&before, "seasonloc_trip_frames_total"), Some(0.0));
    let r = c.request("POST", &format!("/v1/maps/{map}/trips"), None, &[]);
    assert_eq!(r.status, 201);
    let trip = r.json()["id"].as_str().unwrap().to_string();
    let text = String::from_utf8(c.get("/metrics").body).unwrap();
    assert_eq!(
        sample(&text, "seasonloc_trips_open{status=\"new\"}"),
        Some(1.0),
        "{text}"
    );
    for batch in 0..2u32 {
        let parts: Vec<Part> = (batch * 10..batch * 10 + 10)
            .map(|i| Part::image(&format!("q{i}.png"), route.query_png(i)))
            .collect();
        let r = c.post_multipart(&format!("/v1/trips/{trip}/frames"), &parts);
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    }
    let text = String::from_utf8(c.get("/metrics").body).unwrap();
    assert_eq!(sample(&text, "seasonloc_trip_batches_total"), Some(2.0));
    assert_eq!(sample(&text, "seasonloc_trip_frames_total"), Some(20.0));
    let by_status: f64 = ["localized", "uncertain", "off_map", "lost"]
        .iter()
        .map(|s| {
            sample(
                &text,
                &format!("seasonloc_trip_frames_by_status_total{{status=\"{s}\"}}"),
            )
            .unwrap_or_else(|| panic!("no frames_by_status for {s}"))
        })
        .sum();
    assert_eq!(by_status, 20.0);
    assert_eq!(
        sample(&text, "seasonloc_trip_frame_confidence_count"),
        Some(20.0)
    );
    assert_eq!(
        sample(&text, "seasonloc_trip_batch_duration_seconds_count"),
        Some(2.0)
    );
    let open: f64 = ["new", "localized", "lost", "relocalized"]
        .iter()
        .map(|s| sample(&text, &format!("seasonloc_trips_open{{status=\"{s}\"}}")).unwrap())
        .sum();
    assert_eq!(open, 1.0);
    assert_eq!(
        sample(&text, "seasonloc_trips_open{status=\"new\"}"),
        Some(0.0)
    );
    assert!(
        sample(
            &text,
            "seasonloc_store_operation_duration_seconds_count{operation=\"put_trip_batch\"}"
        )
        .unwrap()
            >= 2.0
    );
    assert!(
        sample(
            &text,
            "seasonloc_descriptor_cache_bytes{descriptor=\"hog\"}"
        )
        .unwrap()
            > 0.0
    );
    assert_eq!(
        sample(&text, "seasonloc_descriptor_cache_maps{descriptor=\"hog\"}"),
        Some(1.0)
    );
    assert!(text.contains("seasonloc_build_info{version=\""), "{text}");
    for family in [
        "process_resident_memory_bytes",
        "process_cpu_seconds_total",
        "process_open_fds",
        "process_max_fds",
        "process_start_time_seconds",
    ] {
        assert!(sample(&text, family).unwrap() > 0.0, "{family}");
    }
    assert!(sample(&text, "seasonloc_localize_queue_depth").is_some());

    let r = c.request("POST", &format!("/v1/trips/{trip}/close"), None, &[]);
    assert_eq!(r.status, 200);
    let text = String::from_utf8(c.get("/metrics").body).unwrap();
    let open: f64 = ["new", "localized", "lost", "relocalized"]
        .iter()
        .map(|s| sample(&text, &format!("seasonloc_trips_open{{status=\"{s}\"}}")).unwrap())
        .sum();
    assert_eq!(open, 0.0);
}
