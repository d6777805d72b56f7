//! What only a shared database gives: several replicas serving one PostgreSQL database (any
//! replica answers any request with the result a single embedded-store server gives), and a
//! database that goes away and comes back under a running replica.

use serde_json::{json, Value};

use crate::common::{create_hog_map, engine_database, Route, Server};
use crate::http::{Client, Part};
use crate::spec::check;
use seasonloc_test_support::postgres as testing;

fn body(r: &crate::http::Response) -> String {
    String::from_utf8_lossy(&r.body).into_owned()
}

/// A replica of the service on the database at `url`.
fn replica(url: &str) -> Server {
    let url = url.to_string();
    Server::start_with(move |a| a.database_url = Some(url))
}

/// A server on the embedded store, for comparison.
fn embedded() -> Server {
    Server::start_with(|a| a.database_url = None)
}

fn upload(c: &Client, map: &str, route: &Route, frames: std::ops::Range<u32>) {
    let parts: Vec<Part> = frames
        .map(|i| Part::image(&format!("r{i}.png"), route.reference_png(i)))
        .collect();
    let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &parts);
    assert_eq!(r.status, 200, "{}", body(&r));
}

fn queries(route: &Route, frames: std::ops::Range<u32>) -> Vec<Part> {
    frames
        .map(|i| Part::image(&format!("q{i}.png"), route.query_png(i)))
        .collect()
}

fn image_count(c: &Client, map: &str) -> u64 {
    c.get(&format!("/v1/maps/{map}")).json()["image_count"]
        .as_u64()
        .unwrap_or(0)
}

#[test]
fn two_replicas_share_maps_images_and_results() {
    let Some(url) = engine_database() else { return };
    let (a, b) = (replica(&url), replica(&url));
    let route = Route::new(60, 11);
    let map = create_hog_map(&a.client, "shared", 8);
    // Uploads on both replicas interleave into one route order.
    upload(&a.client, &map, &route, 0..20);
    upload(&b.client, &map, &route, 20..40);
    upload(&a.client, &map, &route, 40..60);
    assert_eq!(image_count(&a.client, &map), 60);
    assert_eq!(image_count(&b.client, &map), 60);
    // B localizes (its cache is filled from the database), A reads B's stored result.
    let r = b.client.post_multipart(
        &format!("/v1/maps/{map}/localize"),
        &queries(&route, 25..45),
    );
    assert_eq!(r.status, 200, "{}", body(&r));
    let result = r.json();
    assert_eq!(result["reference_count"], 60);
    let id = result["id"].as_str().unwrap();
    let read = a.client.get(&format!("/v1/localizations/{id}"));
    assert_eq!(read.status, 200, "{}", body(&read));
    assert_eq!(read.json()["predictions"], result["predictions"]);
    // The queries are frames 25..45: the images uploaded on B were used.
    let hits = result["predictions"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| {
            let (q, r) = (p["query"].as_u64().unwrap(), p["ref"].as_u64().unwrap());
            r.abs_diff(q + 25) <= 1
        })
        .count();
    assert!(hits >= 12, "{hits}/20 queries matched: {result}");
    // The same upload and query on one embedded server give the same predictions.
    let single = embedded();
    let smap = create_hog_map(&single.client, "single", 8);
    upload(&single.client, &smap, &route, 0..60);
    let s = single.client.post_multipart(
        &format!("/v1/maps/{smap}/localize"),
        &queries(&route, 25..45),
    );
    assert_eq!(s.json()["predictions"], result["predictions"]);
    // A deletion on A is seen by B.
    assert_eq!(a.client.delete(&format!("/v1/maps/{map}")).status, 204);
    assert_eq!(b.client.get(&format!("/v1/maps/{map}")).status, 404);
    assert_eq!(b.client.get(&format!("/v1/localizations/{id}")).status, 404);
}

/// Posts frames `range` of `route` to trip `trip`.
fn post_frames(c: &Client, trip: &str, route: &Route, range: std::ops::Range<u32>) -> Value {
    let r = c.post_multipart(&format!("/v1/trips/{trip}/frames"), &queries(route, range));
    assert_eq!(r.status, 200, "{}", body(&r));
    r.json()
}

fn open_trip(c: &Client, map: &str) -> String {
    let r = c.post_json(&format!("/v1/maps/{map}/trips"), &json!({"lag": 8}));
    assert_eq!(r.status, 201, "{}", body(&r));
    r.json()["id"].as_str().unwrap().to_string()
}

#[test]
fn a_trip_alternating_between_replicas_equals_the_trip_on_one_embedded_server() {
    let Some(url) = engine_database() else { return };
    let (a, b) = (replica(&url), replica(&url));
    let single = embedded();
    let route = Route::new(80, 5);
    let map = create_hog_map(&a.client, "fleet", 8);
    upload(&b.client, &map, &route, 0..80);
    let smap = create_hog_map(&single.client, "single", 8);
    upload(&single.client, &smap, &route, 0..80);
    let trip = open_trip(&a.client, &map);
    let strip = open_trip(&single.client, &smap);
    for (k, lo) in (10..60).step_by(5).enumerate() {
        let c = if k % 2 == 0 { &a.client } else { &b.client };
        let got = post_frames(c, &trip, &route, lo..lo + 5);
        let want = post_frames(&single.client, &strip, &route, lo..lo + 5);
        assert_eq!(got["frame_count"], want["frame_count"]);
        assert_eq!(got["estimates"], want["estimates"], "batch {k}");
        assert_eq!(got["status"], want["status"], "batch {k}");
    }
    let (ta, ts) = (
        b.client.get(&format!("/v1/trips/{trip}")).json(),
        single.client.get(&format!("/v1/trips/{strip}")).json(),
    );
    assert_eq!(ta["frame_count"], 50);
    assert_eq!(ta["estimates"], ts["estimates"]);
}

#[test]
fn concurrent_batches_of_one_trip_on_two_replicas_both_apply_one_after_the_other() {
    let Some(url) = engine_database() else { return };
    let (a, b) = (replica(&url), replica(&url));
    let route = Route::new(60, 9);
    let map = create_hog_map(&a.client, "race", 8);
    upload(&a.client, &map, &route, 0..60);
    let trip = open_trip(&a.client, &map);
    let results: Vec<Value> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..6u32)
            .map(|k| {
                let c = if k % 2 == 0 { &a.client } else { &b.client };
                let (trip, route) = (&trip, &route);
                s.spawn(move || post_frames(c, trip, route, 10 + 4 * k..14 + 4 * k))
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    // Every batch applied exactly once: the counts seen are 4, 8, ..., 24 in some order.
    let mut counts: Vec<u64> = results
        .iter()
        .map(|r| r["frame_count"].as_u64().unwrap())
        .collect();
    counts.sort_unstable();
    assert_eq!(counts, vec![4, 8, 12, 16, 20, 24]);
    let t = a.client.get(&format!("/v1/trips/{trip}")).json();
    assert_eq!(t["estimates"].as_array().unwrap().len(), 24);
}

#[test]
fn a_database_outage_answers_503_then_the_replica_recovers_by_itself() {
    let Some(bin) = testing::require("database outage") else {
        return;
    };
    // Its own server: this test stops it.
    let pg = testing::TestServer::start(&bin).unwrap();
    let url = pg.database().unwrap();
    let a = Server::start_with({
        let url = url.clone();
        move |s| {
            s.database_url = Some(url);
            s.request_timeout_secs = 20;
            s.localize_max_wait_secs = 10;
        }
    });
    let route = Route::new(40, 3);
    let map = create_hog_map(&a.client, "outage", 8);
    upload(&a.client, &map, &route, 0..40);
    let trip = open_trip(&a.client, &map);
    post_frames(&a.client, &trip, &route, 5..10);

    pg.pause().unwrap();
    let started = std::time::Instant::now();
    let ready = a.client.get("/readyz");
    assert_eq!(ready.status, 503, "{}", body(&ready));
    for (method, template, r) in [
        (
            "post",
            "/v1/maps/{id}/trips",
            a.client
                .post_json(&format!("/v1/maps/{map}/trips"), &json!({})),
        ),
        (
            "post",
            "/v1/trips/{id}/frames",
            a.client.post_multipart(
                &format!("/v1/trips/{trip}/frames"),
                &queries(&route, 10..15),
            ),
        ),
        (
            "get",
            "/v1/maps/{id}",
            a.client.get(&format!("/v1/maps/{map}")),
        ),
        ("get", "/v1/maps", a.client.get("/v1/maps")),
    ] {
        assert_eq!(r.status, 503, "{method} {template}: {}", body(&r));
        assert_eq!(r.code(), "not_ready", "{method} {template}");
        assert!(r.header("retry-after").is_some(), "{method} {template}");
        check(method, template, &r);
    }
    // Failing fast, not waiting for the request timeout.
    assert!(
        started.elapsed() < std::time::Duration::from_secs(20),
        "{:?}",
        started.elapsed()
    );

    pg.resume().unwrap();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    while a.client.get("/readyz").status != 200 {
        assert!(std::time::Instant::now() < deadline, "not ready again");
        std::thread::sleep(std::time::Duration::from_millis(200));
    }
    // Nothing was lost or half-applied: the failed batch did not count.
    let r = post_frames(&a.client, &trip, &route, 10..15);
    assert_eq!(r["frame_count"], 10);
    assert_eq!(image_count(&a.client, &map), 40);
}

#[test]
fn a_batch_in_flight_on_a_killed_replica_is_applied_once_when_retried_on_another() {
    let Some(url) = engine_database() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let start = |name: &str| {
        crate::common::Process::start(
            &["--addr", "127.0.0.1:0", "--database-url", &url],
            &[],
            &tmp.path().join(format!("{name}.log")),
        )
    };
    let (a, b) = (start("a"), start("b"));
    let route = Route::new(60, 13);
    let map = create_hog_map(&a.client, "sigkill", 8);
    upload(&b.client, &map, &route, 0..60);
    let trip = open_trip(&a.client, &map);
    let path = format!("/v1/trips/{trip}/frames");
    let key = [("Idempotency-Key", "k0")];
    let r = a
        .client
        .post_multipart_with(&path, &queries(&route, 0..10), &key)
        .unwrap();
    assert_eq!(r.status, 200, "{}", body(&r));
    // Batch k1 goes to A, which is killed while it is (or may be) in flight.
    let parts = queries(&route, 10..20);
    let client_a = a.client;
    let in_flight = {
        let (path, parts) = (path.clone(), queries(&route, 10..20));
        std::thread::spawn(move || {
            let _ = client_a.post_multipart_with(&path, &parts, &[("Idempotency-Key", "k1")]);
        })
    };
    std::thread::sleep(std::time::Duration::from_millis(30));
    a.kill();
    let _ = in_flight.join();
    // The client retries on B: applied exactly once, whether A committed it or not.
    let retry = b
        .client
        .post_multipart_with(&path, &parts, &[("Idempotency-Key", "k1")])
        .unwrap();
    assert_eq!(retry.status, 200, "{}", body(&retry));
    assert_eq!(retry.json()["frame_count"], 20);
    let again = b
        .client
        .post_multipart_with(&path, &parts, &[("Idempotency-Key", "k1")])
        .unwrap();
    assert_eq!(again.json()["frame_count"], 20);
    assert_eq!(again.header("idempotent-replayed"), Some("true"));
    let t = b.client.get(&format!("/v1/trips/{trip}")).json();
    assert_eq!(t["frame_count"], 20);
    assert_eq!(t["estimates"].as_array().unwrap().len(), 20);
    // And it equals the same trip on one embedded server.
    let single = embedded();
    let smap = create_hog_map(&single.client, "single", 8);
    upload(&single.client, &smap, &route, 0..60);
    let strip = open_trip(&single.client, &smap);
    post_frames(&single.client, &strip, &route, 0..10);
    post_frames(&single.client, &strip, &route, 10..20);
    let s = single.client.get(&format!("/v1/trips/{strip}")).json();
    assert_eq!(t["estimates"], s["estimates"]);
}
