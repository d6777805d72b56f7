//! Trip ownership over HTTP (issue 42, defect 8): the key that opens a trip is its `opened_by`;
//! another vehicle key may read the trip but neither post frames to it nor close it (403
//! `forbidden`, the trip unchanged); the opener and an admin key may.

use serde_json::json;
use sha2::{Digest, Sha256};

use crate::common::{Route, Server};
use crate::http::{multipart_body, Client, Part, Response, BOUNDARY};

const ADMIN: &str = "adm-7d0e4b1c9a2f6e35";
const VEHICLE_A: &str = "veh-a-3c9b1e7f5d2a8064";
const VEHICLE_B: &str = "veh-b-8e2d6a0c4f1b9375";

fn sha(key: &str) -> String {
    Sha256::digest(key.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

fn call(
    c: &Client,
    method: &str,
    path: &str,
    key: &str,
    ct: Option<&str>,
    body: &[u8],
) -> Response {
    let auth = format!("Bearer {key}");
    c.request_with(method, path, &[("Authorization", auth.as_str())], ct, body)
}

#[test]
fn only_the_opener_or_an_admin_extends_or_closes_a_trip() {
    let dir = tempfile::tempdir().unwrap();
    let keys = dir.path().join("keys.json");
    let entries: Vec<_> = [
        ("ops", "admin", ADMIN),
        ("vehicle-a", "vehicle", VEHICLE_A),
        ("vehicle-b", "vehicle", VEHICLE_B),
    ]
    .iter()
    .map(|(name, role, key)| json!({"name": name, "role": role, "sha256": sha(key)}))
    .collect();
    std::fs::write(&keys, json!({ "keys": entries }).to_string()).unwrap();
    let server = Server::start_with(|a| a.api_keys = Some(keys.clone()));
    let c = &server.client;
    let json_ct = Some("application/json");
    let create = json!({"name": "owned", "descriptor": {"kind": "hog", "cell_size": 8}});
    let r = call(
        c,
        "POST",
        "/v1/maps",
        ADMIN,
        json_ct,
        create.to_string().as_bytes(),
    );
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let map = r.json()["id"].as_str().unwrap().to_string();
    let route = Route::new(20, 11);
    let ct = format!("multipart/form-data; boundary={BOUNDARY}");
    let pngs = |range: std::ops::Range<u32>, query: bool| {
        let parts: Vec<Part> = range
            .map(|i| {
                let png = if query {
                    route.query_png(i)
                } else {
                    route.reference_png(i)
                };
                Part::image(&format!("{i}.png"), png)
            })
            .collect();
        multipart_body(&parts)
    };
    let r = call(
        c,
        "POST",
        &format!("/v1/maps/{map}/images"),
        ADMIN,
        Some(&ct),
        &pngs(0..20, false),
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let r = call(
        c,
        "POST",
        &format!("/v1/maps/{map}/trips"),
        VEHICLE_A,
        json_ct,
        b"{}",
    );
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["opened_by"], "vehicle-a");
    crate::spec::check("post", "/v1/maps/{id}/trips", &r);
    let trip = r.json()["id"].as_str().unwrap().to_string();
    let frames = format!("/v1/trips/{trip}/frames");
    let close = format!("/v1/trips/{trip}/close");
    let read = || call(c, "GET", &format!("/v1/trips/{trip}"), VEHICLE_B, None, b"").json();

    let r = call(c, "POST", &frames, VEHICLE_B, Some(&ct), &pngs(0..4, true));
    assert_eq!(
        (r.status, r.code().as_str()),
        (403, "forbidden"),
        "{}",
        r.message()
    );
    assert!(r.message().contains("vehicle-a"), "{}", r.message());
    crate::spec::check("post", "/v1/trips/{id}/frames", &r);
    let r = call(c, "POST", &close, VEHICLE_B, None, b"");
    assert_eq!(
        (r.status, r.code().as_str()),
        (403, "forbidden"),
        "{}",
        r.message()
    );
    let t = read();
    assert_eq!(
        (t["frame_count"].as_u64(), t["closed_at_ms"].is_null()),
        (Some(0), true)
    );

    let r = call(c, "POST", &frames, VEHICLE_A, Some(&ct), &pngs(0..4, true));
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let r = call(c, "POST", &frames, ADMIN, Some(&ct), &pngs(4..8, true));
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let r = call(c, "POST", &close, ADMIN, None, b"");
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    crate::spec::check("post", "/v1/trips/{id}/close", &r);
    let t = read();
    assert_eq!(
        (t["frame_count"].as_u64(), t["closed_at_ms"].is_null()),
        (Some(8), false)
    );
    assert_eq!(t["opened_by"], "vehicle-a");

    let r = call(
        c,
        "POST",
        &format!("/v1/maps/{map}/trips"),
        VEHICLE_A,
        json_ct,
        b"{}",
    );
    let own = r.json()["id"].as_str().unwrap().to_string();
    let r = call(
        c,
        "POST",
        &format!("/v1/trips/{own}/close"),
        VEHICLE_A,
        None,
        b"",
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
}
