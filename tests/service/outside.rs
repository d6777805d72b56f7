//! Regression tests of what the second outside reliability test found (issue 42): metric labels
//! a keyless client could grow, a batch of decompression bombs under a memory limit, slow
//! bodies holding the localize queue and the probes, CSRF and DNS rebinding on keyless
//! loopback serving, half-open connections starving probes, unbounded request ids, and a
//! localization without predictions that did not say why.
//!
//! Every server listens on 127.0.0.1; every load is bounded in count and time.

use std::path::Path;

use serde_json::json;
use sha2::{Digest, Sha256};

use crate::common::Server;
use crate::http::Client;

const ADMIN: &str = "adm-42c1f0e9d8b7a6";
const READER: &str = "rd-42e5d4c3b2a190";

/// A key file with an admin and a reader key.
fn write_keys(path: &Path) {
    let entry = |name: &str, role: &str, key: &str| {
        let sha: String = Sha256::digest(key.as_bytes())
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        json!({"name": name, "role": role, "sha256": sha})
    };
    let keys = json!({"keys": [entry("ops", "admin", ADMIN), entry("wall", "reader", READER)]});
    std::fs::write(path, keys.to_string()).unwrap();
}

fn bearer(key: &str) -> String {
    format!("Bearer {key}")
}

// ---- 1: metric labels --------------------------------------------------------------------------

#[test]
fn distinct_long_methods_never_become_metric_labels() {
    let dir = tempfile::tempdir().unwrap();
    let keys = dir.path().join("keys.json");
    write_keys(&keys);
    let server = Server::start_with(|a| a.api_keys = Some(keys.clone()));
    let c = server.client;
    let reader = bearer(READER);
    let metrics =
        |c: &Client| c.request_with("GET", "/metrics", &[("Authorization", &reader)], None, b"");
    let before = metrics(&c).body.len();
    // 300 requests without a key, each with its own 1,000-character method (answered before
    // any key is checked for, or with 401).
    for n in 0..300 {
        let method = format!("M{n:07}{}", "X".repeat(992));
        let path = if n % 2 == 0 { "/healthz" } else { "/v1/maps" };
        let r = c.request(&method, path, None, b"");
        assert!(r.status >= 400, "{n}: {}", r.status);
    }
    let r = metrics(&c);
    assert_eq!(r.status, 200);
    let text = String::from_utf8(r.body).unwrap();
    assert!(
        !text.contains("XXXXXXXX"),
        "a client's method became a label"
    );
    assert!(
        text.contains("method=\"other\""),
        "extension methods are counted under `other`"
    );
    // A few more series (`other` per route and status), not one per request.
    assert!(
        text.len() < before + 8_000,
        "/metrics grew from {before} to {} bytes",
        text.len()
    );
}
