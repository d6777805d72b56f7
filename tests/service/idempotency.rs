//! `Idempotency-Key` on every route that creates or appends: `POST /v1/maps`,
//! `POST /v1/maps/{id}/images`, `/descriptors`, `/drives`, `/trips`, `/localize` and
//! `POST /v1/trips/{id}/frames` (on the embedded store in `service`, on PostgreSQL in
//! `service_pg`): a retry with the same key and content is applied once and answered as the
//! first time; the key with other content is 409.

use serde_json::{json, Value};

use crate::common::{create_hog_map, create_vector_map, Route, Server};
use crate::http::{Client, Part, Response};
use crate::spec::check;

fn body(r: &Response) -> String {
    String::from_utf8_lossy(&r.body).into_owned()
}

fn frames(route: &Route, range: std::ops::Range<u32>) -> Vec<Part> {
    range
        .map(|i| Part::image(&format!("q{i}.png"), route.query_png(i)))
        .collect()
}

fn refs(route: &Route, range: std::ops::Range<u32>) -> Vec<Part> {
    range
        .map(|i| Part::image(&format!("r{i}.png"), route.reference_png(i)))
        .collect()
}

fn post(c: &Client, path: &str, parts: &[Part], key: &str) -> Response {
    c.post_multipart_with(path, parts, &[("Idempotency-Key", key)])
        .unwrap()
}

/// A `POST` of `bytes` as `content_type` with an `Idempotency-Key`, checked against the
/// document's entry `template`.
fn post_keyed(
    c: &Client,
    path: &str,
    template: &str,
    content_type: &str,
    bytes: &[u8],
    key: &str,
) -> Response {
    let r = c.request_with(
        "POST",
        path,
        &[("Idempotency-Key", key)],
        Some(content_type),
        bytes,
    );
    check("POST", template, &r);
    r
}

/// A JSON `POST` of `value` with an `Idempotency-Key` ([`post_keyed`]).
fn post_json_keyed(c: &Client, path: &str, template: &str, value: &Value, key: &str) -> Response {
    let bytes = serde_json::to_vec(value).unwrap();
    post_keyed(c, path, template, "application/json", &bytes, key)
}

/// The key was used for another request: 409 `idempotency_key_reused`.
fn assert_reused(r: &Response, what: &str) {
    assert_eq!(
        (r.status, r.code().as_str()),
        (409, "idempotency_key_reused"),
        "{what}: {}",
        body(r)
    );
}

/// `send` four times at once: retries of one request racing each other.
fn four_at_once(send: impl Fn() -> Response + Sync) -> Vec<Response> {
    std::thread::scope(|s| {
        let hs: Vec<_> = (0..4).map(|_| s.spawn(&send)).collect();
        hs.into_iter().map(|h| h.join().unwrap()).collect()
    })
}

/// Four racing retries of one creation ([`four_at_once`]) made one object: every answer is 201
/// with the same id, and three of them are replays.
fn created_once(answers: &[Response]) {
    let ids: std::collections::HashSet<String> = answers
        .iter()
        .map(|a| {
            assert_eq!(a.status, 201, "{}", body(a));
            a.json()["id"].as_str().unwrap().to_string()
        })
        .collect();
    assert_eq!(ids.len(), 1);
    let replays = answers
        .iter()
        .filter(|a| a.header("idempotent-replayed").is_some())
        .count();
    assert_eq!(replays, 3);
}

/// The answer without its timings (a replay reports none).
fn without_timings(v: &Value) -> Value {
    let mut v = v.clone();
    v.as_object_mut().unwrap().remove("timings");
    v
}

#[test]
fn a_retried_batch_of_frames_is_applied_once_and_answered_the_same() {
    let server = Server::start();
    let c = &server.client;
    let route = Route::new(40, 21);
    let map = create_hog_map(c, "idem", 8);
    assert_eq!(
        c.post_multipart(&format!("/v1/maps/{map}/images"), &refs(&route, 0..40))
            .status,
        200
    );
    let r = c.post_json(&format!("/v1/maps/{map}/trips"), &json!({"lag": 8}));
    let trip = r.json()["id"].as_str().unwrap().to_string();
    let path = format!("/v1/trips/{trip}/frames");

    let first = post(c, &path, &frames(&route, 5..10), "batch-1");
    check("POST", "/v1/trips/{id}/frames", &first);
    assert_eq!(first.status, 200, "{}", body(&first));
    assert_eq!(first.header("idempotent-replayed"), None);
    let again = post(c, &path, &frames(&route, 5..10), "batch-1");
    check("POST", "/v1/trips/{id}/frames", &again);
    assert_eq!(again.status, 200, "{}", body(&again));
    assert_eq!(again.header("idempotent-replayed"), Some("true"));
    assert_eq!(
        without_timings(&again.json()),
        without_timings(&first.json())
    );
    assert_eq!(again.json()["frame_count"], 5);

    // The next batch continues from 5 frames, and the old key still answers the old batch.
    let second = post(c, &path, &frames(&route, 10..15), "batch-2");
    assert_eq!(second.json()["frame_count"], 10);
    let late = post(c, &path, &frames(&route, 5..10), "batch-1");
    assert_eq!(late.json()["frame_count"], 5);
    let t = c.get(&format!("/v1/trips/{trip}")).json();
    assert_eq!(t["frame_count"], 10);
    assert_eq!(t["estimates"].as_array().unwrap().len(), 10);

    // The key of another batch: refused, nothing applied.
    let reused = post(c, &path, &frames(&route, 15..20), "batch-2");
    check("POST", "/v1/trips/{id}/frames", &reused);
    assert_reused(&reused, "reused");
    assert_eq!(
        c.get(&format!("/v1/trips/{trip}")).json()["frame_count"],
        10
    );
    // A malformed key.
    let bad = post(c, &path, &frames(&route, 15..20), "two words");
    check("POST", "/v1/trips/{id}/frames", &bad);
    assert_eq!(
        (bad.status, bad.code().as_str()),
        (400, "invalid_parameter")
    );
    assert_eq!(
        c.get(&format!("/v1/trips/{trip}")).json()["frame_count"],
        10
    );
}

#[test]
fn a_retried_batch_of_images_is_stored_once() {
    let server = Server::start();
    let c = &server.client;
    let route = Route::new(30, 22);
    let map = create_hog_map(c, "idem-images", 8);
    let path = format!("/v1/maps/{map}/images");
    let first = post(c, &path, &refs(&route, 0..10), "upload-a");
    check("POST", "/v1/maps/{id}/images", &first);
    assert_eq!(first.status, 200, "{}", body(&first));
    let second = post(c, &path, &refs(&route, 10..20), "upload-b");
    assert_eq!(second.json()["image_count"], 20);
    let again = post(c, &path, &refs(&route, 0..10), "upload-a");
    check("POST", "/v1/maps/{id}/images", &again);
    assert_eq!(again.status, 200, "{}", body(&again));
    assert_eq!(again.header("idempotent-replayed"), Some("true"));
    assert_eq!(again.json(), first.json());
    let map_now = c.get(&format!("/v1/maps/{map}")).json();
    assert_eq!(map_now["image_count"], 20);
    let reused = post(c, &path, &refs(&route, 20..30), "upload-a");
    assert_reused(&reused, "reused");
    // Keys are per map: the same key on another map is a new request.
    let other = create_hog_map(c, "other", 8);
    let r = post(
        c,
        &format!("/v1/maps/{other}/images"),
        &refs(&route, 0..10),
        "upload-a",
    );
    assert_eq!(r.header("idempotent-replayed"), None);
    assert_eq!(r.json()["image_count"], 10);
}

#[test]
fn concurrent_retries_of_one_batch_apply_it_once() {
    let server = Server::start();
    let c = &server.client;
    let route = Route::new(40, 23);
    let map = create_hog_map(c, "idem-race", 8);
    c.post_multipart(&format!("/v1/maps/{map}/images"), &refs(&route, 0..40));
    let r = c.post_json(&format!("/v1/maps/{map}/trips"), &json!({}));
    let trip = r.json()["id"].as_str().unwrap().to_string();
    let path = format!("/v1/trips/{trip}/frames");
    let parts = frames(&route, 0..6);
    let answers = four_at_once(|| post(c, &path, &parts, "same"));
    for a in &answers {
        assert_eq!(a.status, 200, "{}", body(a));
        assert_eq!(a.json()["frame_count"], 6);
    }
    let replays = answers
        .iter()
        .filter(|a| a.header("idempotent-replayed").is_some())
        .count();
    assert_eq!(replays, 3);
    assert_eq!(c.get(&format!("/v1/trips/{trip}")).json()["frame_count"], 6);
}

#[test]
fn a_retried_batch_of_descriptors_is_stored_once() {
    let server = Server::start();
    let c = &server.client;
    let map = create_vector_map(c, "idem-descriptors", 4);
    let path = format!("/v1/maps/{map}/descriptors");
    let send = |ct: &str, query: &str, bytes: &[u8], key: &str| {
        let t = "/v1/maps/{id}/descriptors";
        post_keyed(c, &format!("{path}{query}"), t, ct, bytes, key)
    };
    let json_body =
        serde_json::to_vec(&json!({"descriptors": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]]}))
            .unwrap();
    let first = send("application/json", "", &json_body, "desc-a");
    assert_eq!(first.status, 200, "{}", body(&first));
    assert_eq!(first.json()["indices"], json!([0, 1]));
    assert_eq!(first.header("idempotent-replayed"), None);
    let again = send("application/json", "", &json_body, "desc-a");
    assert_eq!(again.status, 200, "{}", body(&again));
    assert_eq!(again.header("idempotent-replayed"), Some("true"));
    assert_eq!(again.json(), first.json());
    assert_eq!(c.get(&format!("/v1/maps/{map}")).json()["image_count"], 2);

    // A raw body: the same, and its `?dim=` and media type are part of the request.
    let raw: Vec<u8> = [0.5f32, 0.5, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let octet = "application/octet-stream";
    let first = send(octet, "?dim=4", &raw, "desc-b");
    assert_eq!(first.json()["indices"], json!([2, 3]));
    let again = send(octet, "?dim=4", &raw, "desc-b");
    assert_eq!(again.header("idempotent-replayed"), Some("true"));
    assert_eq!(again.json(), first.json());
    assert_eq!(c.get(&format!("/v1/maps/{map}")).json()["image_count"], 4);
    for (ct, query, bytes) in [
        (octet, "?dim=4", &raw[..16]),
        (octet, "", &raw[..]),
        ("application/json", "", &json_body[..]),
    ] {
        let reused = send(ct, query, bytes, "desc-b");
        assert_reused(&reused, &format!("{ct} {query}"));
    }
    assert_eq!(c.get(&format!("/v1/maps/{map}")).json()["image_count"], 4);
}

#[test]
fn a_retried_drive_is_fused_once() {
    let server = Server::start();
    let c = &server.client;
    let route = Route::new(30, 24);
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": "idem-drives", "descriptor": {"kind": "cooc", "vocabulary_branching": 8}}),
    );
    assert_eq!(r.status, 201, "{}", body(&r));
    let map = r.json()["id"].as_str().unwrap().to_string();
    let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &refs(&route, 0..30));
    assert_eq!(r.status, 200, "{}", body(&r));
    let path = format!("/v1/maps/{map}/drives");
    let drive_parts = |frames: std::ops::Range<u32>, time: f64| {
        let mut p: Vec<Part> = frames
            .clone()
            .map(|i| Part::image(&format!("n{i}.png"), route.query_png(i)))
            .collect();
        let locations: Vec<u32> = frames.collect();
        p.push(Part::json(
            "drive",
            &json!({"locations": locations, "time": time}),
        ));
        p
    };
    let send = |parts: &[Part], key: Option<&str>| {
        let headers: Vec<(&str, &str)> = key.map(|k| ("Idempotency-Key", k)).into_iter().collect();
        let r = c.post_multipart_with(&path, parts, &headers).unwrap();
        check("POST", "/v1/maps/{id}/drives", &r);
        assert!(
            r.status == 200 || r.status == 409,
            "{}: {}",
            r.status,
            body(&r)
        );
        r
    };
    let a = drive_parts(0..10, 20.0);
    let first = send(&a, Some("drive-a"));
    assert_eq!(first.json(), json!({"drives": 2, "images": 10}));
    let again = send(&a, Some("drive-a"));
    assert_eq!(again.header("idempotent-replayed"), Some("true"));
    assert_eq!(again.json(), first.json());
    // The replay fused nothing: the next drive is the third.
    let b = send(&drive_parts(10..20, 21.0), None);
    assert_eq!(b.json(), json!({"drives": 3, "images": 10}));
    let again = send(&a, Some("drive-a"));
    assert_eq!(again.json(), first.json());
    let c_ = send(&drive_parts(20..30, 22.0), None);
    assert_eq!(c_.json()["drives"], 4);
    // The key with another drive, or sent to the map's image appends, is another request.
    let reused = send(&drive_parts(0..10, 23.0), Some("drive-a"));
    assert_reused(&reused, "reused");
    let images = post(c, &format!("/v1/maps/{map}/images"), &a[..10], "drive-a");
    assert_reused(&images, "images");
    assert_eq!(send(&drive_parts(0..5, 24.0), None).json()["drives"], 5);
}

#[test]
fn a_retried_trip_opening_opens_one_trip() {
    let server = Server::start();
    let c = &server.client;
    let route = Route::new(20, 25);
    let map = create_hog_map(c, "idem-trips", 8);
    let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &refs(&route, 0..20));
    assert_eq!(r.status, 200, "{}", body(&r));
    let path = format!("/v1/maps/{map}/trips");
    let open =
        |params: &Value, key: &str| post_json_keyed(c, &path, "/v1/maps/{id}/trips", params, key);
    let params = json!({"lag": 8});
    let first = open(&params, "open-a");
    assert_eq!(first.status, 201, "{}", body(&first));
    assert_eq!(first.header("idempotent-replayed"), None);
    let again = open(&params, "open-a");
    assert_eq!(again.status, 201, "{}", body(&again));
    assert_eq!(again.header("idempotent-replayed"), Some("true"));
    assert_eq!(again.json(), first.json());
    // The replay answers the trip as it is now.
    let trip = first.json()["id"].as_str().unwrap().to_string();
    let r = c.post_multipart(&format!("/v1/trips/{trip}/frames"), &frames(&route, 0..3));
    assert_eq!(r.status, 200, "{}", body(&r));
    let later = open(&params, "open-a");
    assert_eq!(later.json()["id"], first.json()["id"]);
    assert_eq!(later.json()["frame_count"], 3);
    let listed = c.get(&format!("/v1/maps/{map}/trips")).json();
    assert_eq!(listed["items"].as_array().unwrap().len(), 1, "{listed}");
    // Other parameters, or a key of the map's image appends, are another request.
    let other = open(&json!({"lag": 9}), "open-a");
    assert_reused(&other, "other");
    post(
        c,
        &format!("/v1/maps/{map}/images"),
        &refs(&route, 0..2),
        "img-1",
    );
    let shared = open(&params, "img-1");
    assert_reused(&shared, "shared");
    let fresh = open(&params, "open-b");
    assert_eq!(fresh.status, 201);
    assert_ne!(fresh.json()["id"], first.json()["id"]);
    // Concurrent retries of one opening: one trip, the others replay it.
    created_once(&four_at_once(|| open(&params, "race")));
    let listed = c.get(&format!("/v1/maps/{map}/trips")).json();
    assert_eq!(listed["items"].as_array().unwrap().len(), 3, "{listed}");
}

#[test]
fn a_retried_map_creation_creates_one_map() {
    let server = Server::start();
    let c = &server.client;
    let create = |spec: &Value, key: &str| post_json_keyed(c, "/v1/maps", "/v1/maps", spec, key);
    let count = || c.get("/v1/maps").json()["maps"].as_array().unwrap().len();
    let spec = json!({"name": "idem-map", "descriptor": {"kind": "hog", "cell_size": 8}});
    let first = create(&spec, "map-a");
    assert_eq!(first.status, 201, "{}", body(&first));
    assert_eq!(first.header("idempotent-replayed"), None);
    let again = create(&spec, "map-a");
    assert_eq!(again.status, 201, "{}", body(&again));
    assert_eq!(again.header("idempotent-replayed"), Some("true"));
    assert_eq!(again.json(), first.json());
    assert_eq!(count(), 1);
    let other = create(
        &json!({"name": "other", "descriptor": {"kind": "hog", "cell_size": 8}}),
        "map-a",
    );
    assert_reused(&other, "other");
    // Concurrent retries: one map, the others replay it.
    created_once(&four_at_once(|| create(&spec, "race")));
    assert_eq!(count(), 2);
    // The key lives as long as its map: after a delete it creates a new one.
    let id = first.json()["id"].as_str().unwrap().to_string();
    assert_eq!(c.delete(&format!("/v1/maps/{id}")).status, 204);
    let after = create(&spec, "map-a");
    assert_eq!(after.status, 201, "{}", body(&after));
    assert_eq!(after.header("idempotent-replayed"), None);
    assert_ne!(after.json()["id"], first.json()["id"]);
    assert_eq!(count(), 2);
}

#[test]
fn a_retried_localization_is_answered_from_the_store() {
    let server = Server::start();
    let c = &server.client;
    let route = Route::new(30, 26);
    let map = create_hog_map(c, "idem-localize", 8);
    let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &refs(&route, 0..30));
    assert_eq!(r.status, 200, "{}", body(&r));
    let path = format!("/v1/maps/{map}/localize");
    let count = || {
        c.get(&format!("/v1/localizations?map={map}")).json()["items"]
            .as_array()
            .unwrap()
            .len()
    };
    let queries = frames(&route, 5..15);
    let first = post(c, &path, &queries, "loc-a");
    check("POST", "/v1/maps/{id}/localize", &first);
    assert_eq!(first.status, 200, "{}", body(&first));
    assert_eq!(first.header("idempotent-replayed"), None);
    let again = post(c, &path, &queries, "loc-a");
    check("POST", "/v1/maps/{id}/localize", &again);
    assert_eq!(again.header("idempotent-replayed"), Some("true"));
    // The stored result itself, timings included: nothing was computed again.
    assert_eq!(again.json(), first.json());
    assert_eq!(count(), 1);
    let other = post(c, &path, &frames(&route, 6..16), "loc-a");
    assert_reused(&other, "other");
    let append_key = post(
        c,
        &format!("/v1/maps/{map}/images"),
        &refs(&route, 0..2),
        "img-x",
    );
    assert_eq!(append_key.status, 200);
    let shared = post(c, &path, &queries, "img-x");
    assert_reused(&shared, "shared");
    let fresh = post(c, &path, &queries, "loc-b");
    assert_eq!(fresh.header("idempotent-replayed"), None);
    assert_ne!(fresh.json()["id"], first.json()["id"]);
    assert_eq!(count(), 2);
}

#[test]
fn a_retried_localization_of_descriptors_is_answered_from_the_store() {
    let server = Server::start();
    let c = &server.client;
    let map = create_vector_map(c, "idem-localize-json", 3);
    let rows: Vec<Vec<f32>> = (0..12)
        .map(|i| {
            let t = i as f32 * 0.5;
            vec![t.sin() + 1.5, t.cos() + 1.5, 1.0]
        })
        .collect();
    let r = c.post_json(
        &format!("/v1/maps/{map}/descriptors"),
        &json!({ "descriptors": rows }),
    );
    assert_eq!(r.status, 200, "{}", body(&r));
    let request = json!({"descriptors": rows[3..9]});
    let path = format!("/v1/maps/{map}/localize");
    let send =
        |value: &Value, key: &str| post_json_keyed(c, &path, "/v1/maps/{id}/localize", value, key);
    let first = send(&request, "json-a");
    assert_eq!(first.status, 200, "{}", body(&first));
    let again = send(&request, "json-a");
    assert_eq!(again.header("idempotent-replayed"), Some("true"));
    assert_eq!(again.json(), first.json());
    let other = json!({"descriptors": rows[2..9]});
    assert_eq!(send(&other, "json-a").status, 409);
}
