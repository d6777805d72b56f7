//! Trips over HTTP: the whole flow on generated images, online == offline on real Nordland
//! frames, a trip that continues identically after SIGKILL and a restart, concurrent trips,
//! and every bad input (nothing stored, the trip unchanged).

use serde_json::{json, Value};

use crate::common::{
    create_hog_map, create_vector_map, nordland, nordland_files, within_one_frame, Process, Route,
    Server,
};
use crate::http::{Client, Part};
use crate::spec::check;

const OPEN: &str = "/v1/maps/{id}/trips";
const FRAMES: &str = "/v1/trips/{id}/frames";
const READ: &str = "/v1/trips/{id}";
const CLOSE: &str = "/v1/trips/{id}/close";

fn body(r: &crate::http::Response) -> String {
    String::from_utf8_lossy(&r.body).into_owned()
}

/// A HOG map (8 px cells) holding reference frames `0..n` of `route`.
fn route_map(c: &Client, route: &Route, n: u32) -> String {
    let map = create_hog_map(c, "trip-route", 8);
    for start in (0..n).step_by(10) {
        let parts: Vec<Part> = (start..(start + 10).min(n))
            .map(|i| Part::image(&format!("r{i}.png"), route.reference_png(i)))
            .collect();
        let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &parts);
        assert_eq!(r.status, 200, "{}", body(&r));
    }
    map
}

fn open(c: &Client, map: &str, params: Option<Value>) -> String {
    let path = format!("/v1/maps/{map}/trips");
    let r = match params {
        Some(p) => c.post_json(&path, &p),
        None => c.request("POST", &path, None, &[]),
    };
    check("POST", OPEN, &r);
    assert_eq!(r.status, 201, "{}", body(&r));
    r.json()["id"].as_str().unwrap().to_string()
}

fn query_parts(route: &Route, frames: std::ops::Range<u32>) -> Vec<Part> {
    frames
        .map(|i| Part::image(&format!("q{i}.png"), route.query_png(i)))
        .collect()
}

fn post_frames(c: &Client, trip: &str, parts: &[Part]) -> Value {
    let r = c.post_multipart(&format!("/v1/trips/{trip}/frames"), parts);
    check("POST", FRAMES, &r);
    assert_eq!(r.status, 200, "{}", body(&r));
    r.json()
}

/// The answer without the parts that legitimately differ between two trips (id, timings).
fn answer(v: &Value) -> Value {
    json!({"estimates": v["estimates"], "status": v["status"], "window": v["window"],
           "hidden_cost": v["hidden_cost"], "frame_count": v["frame_count"]})
}

#[test]
fn trip_flow_on_generated_images() {
    let server = Server::start();
    let c = server.client;
    let route = Route::new(60, 5);
    let map = route_map(&c, &route, 60);
    let trip = open(&c, &map, None);
    let mut last = Value::Null;
    for b in 0..4u32 {
        let v = post_frames(&c, &trip, &query_parts(&route, b * 10..b * 10 + 10));
        let est = v["estimates"].as_array().unwrap();
        assert_eq!(est.len(), 10);
        for (k, e) in est.iter().enumerate() {
            assert_eq!(e["frame"], (b * 10) as usize + k);
        }
        assert_eq!(v["frame_count"], (b + 1) * 10);
        assert!(v["window"].as_array().unwrap().len() <= 32);
        last = v;
    }
    // The route is easy: the latest frames are found within one frame and the trip is localized.
    assert_eq!(last["status"], "localized", "{last}");
    let latest = &last["estimates"][9];
    let j = latest["ref"]
        .as_i64()
        .expect("the last frame is on the map");
    assert!((j - 39).abs() <= 1, "{latest}");
    let r = c.get(&format!("/v1/trips/{trip}"));
    check("GET", READ, &r);
    let t = r.json();
    assert_eq!(t["frame_count"], 40);
    assert_eq!(t["status"], "localized");
    assert_eq!(t["reference_count"], 60);
    assert_eq!(t["params"]["lag"], 32);
    let est = t["estimates"].as_array().unwrap();
    assert_eq!(est.len(), 40);
    // Frames of the final lag window carry the re-traced (latest) estimate.
    for w in last["window"].as_array().unwrap() {
        assert_eq!(&est[w["frame"].as_u64().unwrap() as usize], w);
    }
    let correct = within_one_frame(est);
    assert!(
        correct >= 36,
        "{correct} of 40 frames within one frame: {t}"
    );
    // Listing, newest first.
    let second = open(&c, &map, Some(json!({"lag": 8, "hidden_cost": 1.5})));
    let r = c.get(&format!("/v1/maps/{map}/trips?limit=1"));
    check("GET", OPEN, &r);
    let page = r.json();
    assert_eq!(page["items"][0]["id"], second.as_str());
    assert_eq!(page["items"][0]["params"]["hidden_cost"], 1.5);
    assert!(page["items"][0].get("estimates").is_none());
    let next = page["next"].as_str().unwrap();
    let page2 = c
        .get(&format!("/v1/maps/{map}/trips?limit=1&before={next}"))
        .json();
    assert_eq!(page2["items"][0]["id"], trip.as_str());
    assert_eq!(page2["next"], Value::Null);
    // Close: idempotent, and frames are refused afterwards.
    let r = c.request("POST", &format!("/v1/trips/{trip}/close"), None, &[]);
    check("POST", CLOSE, &r);
    assert_eq!(r.status, 200);
    let closed_at = r.json()["closed_at_ms"].as_u64().unwrap();
    let again = c.request("POST", &format!("/v1/trips/{trip}/close"), None, &[]);
    assert_eq!(again.json()["closed_at_ms"], closed_at);
    let r = c.post_multipart(
        &format!("/v1/trips/{trip}/frames"),
        &query_parts(&route, 40..41),
    );
    check("POST", FRAMES, &r);
    assert_eq!((r.status, r.code()), (409, "trip_closed".into()));
    assert_eq!(
        c.get(&format!("/v1/trips/{trip}")).json()["frame_count"],
        40
    );
    // Deleting the map deletes its trips.
    assert_eq!(c.delete(&format!("/v1/maps/{map}")).status, 204);
    let r = c.get(&format!("/v1/trips/{trip}"));
    check("GET", READ, &r);
    assert_eq!((r.status, r.code()), (404, "trip_not_found".into()));
}

/// Every estimate carries a calibrated `p_correct` and a status; the trip's `tolerance` and
/// `threshold` are taken, reported and kept; out-of-range ones are refused with the field named.
#[test]
fn trip_estimates_carry_p_correct_and_a_status() {
    let server = Server::start();
    let c = server.client;
    let route = Route::new(60, 5);
    let map = route_map(&c, &route, 60);
    let statuses = ["localized", "uncertain", "off_map", "lost"];
    let check_estimate = |e: &Value| {
        let p = e["p_correct"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&p), "{e}");
        let status = e["status"].as_str().unwrap();
        assert!(statuses.contains(&status), "{e}");
        match status {
            "off_map" => assert!(e["ref"].is_null(), "{e}"),
            "localized" | "uncertain" => assert!(e["ref"].is_number(), "{e}"),
            _ => {}
        }
        if e["ref"].is_null() {
            assert_eq!(p, 0.0, "{e}");
        }
    };
    for (threshold, strict) in [(0.9, false), (1.0, true)] {
        let trip = open(
            &c,
            &map,
            Some(json!({"tolerance": 2, "threshold": threshold})),
        );
        // A trip's first frame, alone, is `localized` only when its p_correct says so;
        // otherwise `lost` (not enough evidence yet), never `uncertain` or `off_map`.
        let first = post_frames(&c, &trip, &query_parts(&route, 0..1));
        let e = &first["estimates"][0];
        match e["status"].as_str().unwrap() {
            "lost" => {}
            "localized" => assert!(e["p_correct"].as_f64().unwrap() >= threshold, "{e}"),
            other => panic!("the first frame is {other}: {first}"),
        }
        assert_eq!(first["latest_status"], e["status"], "{first}");
        let mut last = Value::Null;
        for b in 0..3u32 {
            let frames = (b * 10).max(1)..b * 10 + 10;
            last = post_frames(&c, &trip, &query_parts(&route, frames));
            for e in last["estimates"]
                .as_array()
                .unwrap()
                .iter()
                .chain(last["window"].as_array().unwrap())
            {
                check_estimate(e);
                if e["status"] == "localized" {
                    assert!(e["p_correct"].as_f64().unwrap() >= threshold, "{e}");
                }
            }
            // The trip's status follows its latest frame (or says it relocalized).
            let latest = last["estimates"].as_array().unwrap().last().unwrap();
            assert_eq!(last["latest_status"], latest["status"], "{last}");
            if last["status"] == "localized" {
                assert_eq!(latest["status"], "localized", "{last}");
            }
        }
        let t = c.get(&format!("/v1/trips/{trip}")).json();
        assert_eq!(t["params"]["tolerance"], 2, "{t}");
        assert_eq!(t["params"]["threshold"], threshold, "{t}");
        assert_eq!(t["latest_status"], last["latest_status"], "{t}");
        for e in t["estimates"].as_array().unwrap() {
            check_estimate(e);
        }
        // The easy route is localized at the default threshold; nothing reaches p = 1 exactly.
        let localized = t["estimates"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|e| e["status"] == "localized")
            .count();
        if strict {
            assert_eq!(localized, 0, "{t}");
        } else {
            assert!(localized >= 10, "{localized} of 30 frames localized: {t}");
        }
    }
    for (field, bad) in [
        ("threshold", json!(0)),
        ("threshold", json!(1.5)),
        ("tolerance", json!(1001)),
        ("tolerance", json!(-1)),
    ] {
        let r = c.post_json(&format!("/v1/maps/{map}/trips"), &json!({ field: bad }));
        check("POST", OPEN, &r);
        assert_eq!(
            (r.status, r.code()),
            (400, "invalid_parameter".into()),
            "{field} = {bad}: {}",
            body(&r)
        );
        assert!(body(&r).contains(field), "{}", body(&r));
    }
}

#[test]
fn bad_inputs_store_nothing_and_leave_the_trip_unchanged() {
    let server = Server::start_with(|a| a.max_batch_images = 12);
    let c = server.client;
    let route = Route::new(30, 8);
    let map = route_map(&c, &route, 30);
    let trips = format!("/v1/maps/{map}/trips");
    // Bad parameters name the field.
    for (params, field) in [
        (json!({"lag": 0}), "lag"),
        (json!({"fan_out": 5000}), "fan_out"),
        (json!({"hidden_cost": "cheap"}), "hidden_cost"),
        (json!({"hidden_cost": -1.0}), "hidden_cost"),
        (json!({"relocalization_cost": -2.0}), "relocalization_cost"),
        (json!({"prior_weight": -1}), "prior_weight"),
        (json!({"lagg": 3}), "lagg"),
        (json!({"lag": "long"}), "lag"),
    ] {
        let r = c.post_json(&trips, &params);
        check("POST", OPEN, &r);
        assert_eq!(
            (r.status, r.code()),
            (400, "invalid_parameter".into()),
            "{params}"
        );
        assert!(r.message().contains(field), "{params}: {}", r.message());
    }
    // Each field valid, but together meaningless: 422, never 400 (the schema cannot say it).
    let r = c.post_json(
        &trips,
        &json!({"relocalization": false, "relocalization_cost": 2.0}),
    );
    check("POST", OPEN, &r);
    assert_eq!((r.status, r.code()), (422, "inconsistent_parameter".into()));
    assert!(
        r.message().contains("relocalization_cost"),
        "{}",
        r.message()
    );
    let r = c.request("POST", &trips, Some("text/plain"), b"lag=3");
    check("POST", OPEN, &r);
    assert_eq!(r.status, 415);
    let r = c.request("POST", &trips, Some("application/json"), b"{\"lag\": ");
    assert_eq!((r.status, r.code()), (400, "bad_request".into()));
    // Whitespace is not a JSON document (only an absent body takes the defaults).
    for body in [&b"\r"[..], b" \n\t"] {
        let r = c.request("POST", &trips, Some("application/json"), body);
        check("POST", OPEN, &r);
        assert_eq!((r.status, r.code()), (400, "bad_request".into()));
    }
    // Unknown ids.
    let r = c.post_json("/v1/maps/00000000000000ff/trips", &json!({}));
    check("POST", OPEN, &r);
    assert_eq!((r.status, r.code()), (404, "map_not_found".into()));
    for path in ["/v1/trips/00000000000000ff", "/v1/trips/not-an-id"] {
        let r = c.get(path);
        check("GET", READ, &r);
        assert_eq!((r.status, r.code()), (404, "trip_not_found".into()));
    }
    let r = c.post_multipart(
        "/v1/trips/00000000000000ff/frames",
        &query_parts(&route, 0..1),
    );
    assert_eq!((r.status, r.code()), (404, "trip_not_found".into()));
    let r = c.request("POST", "/v1/trips/00000000000000ff/close", None, &[]);
    assert_eq!((r.status, r.code()), (404, "trip_not_found".into()));
    // Map kinds and states that cannot serve a trip.
    let empty = create_hog_map(&c, "empty", 8);
    let r = c.post_json(&format!("/v1/maps/{empty}/trips"), &json!({}));
    check("POST", OPEN, &r);
    assert_eq!((r.status, r.code()), (409, "map_empty".into()));
    let vectors = create_vector_map(&c, "vectors", 3);
    let r = c.post_json(&format!("/v1/maps/{vectors}/trips"), &json!({}));
    assert_eq!((r.status, r.code()), (409, "map_kind".into()));
    // Bad batches on a real trip, interleaved with good ones; an untouched twin trip
    // receives only the good batches and must answer exactly the same.
    let trip = open(&c, &map, None);
    let twin = open(&c, &map, None);
    let frames = format!("/v1/trips/{trip}/frames");
    let first = post_frames(&c, &trip, &query_parts(&route, 0..6));
    assert_eq!(
        answer(&first),
        answer(&post_frames(&c, &twin, &query_parts(&route, 0..6)))
    );
    let mut corrupt = query_parts(&route, 6..9);
    corrupt[1].bytes.truncate(40);
    let r = c.post_multipart(&frames, &corrupt);
    check("POST", FRAMES, &r);
    assert_eq!((r.status, r.code()), (422, "invalid_image".into()));
    assert!(r.message().contains("image[1]"), "{}", r.message());
    let mut wrong_size = query_parts(&route, 6..8);
    // Smaller than one HOG cell (other sizes are brought to the map's geometry).
    wrong_size[0] = Part::image(
        "tiny.png",
        crate::common::png(&image::GrayImage::new(96, 4)),
    );
    let r = c.post_multipart(&frames, &wrong_size);
    assert_eq!((r.status, r.code()), (422, "invalid_image".into()));
    assert!(r.message().contains("tiny.png"), "{}", r.message());
    // Frames are `image` parts only (a trip's parameters are fixed when it is opened).
    let r = c.post_multipart(&frames, &[Part::json("params", &json!({}))]);
    assert_eq!((r.status, r.code()), (400, "bad_request".into()));
    for extra in ["params", "foo"] {
        let mut parts = query_parts(&route, 6..7);
        parts.push(Part::json(extra, &json!({"lag": 3})));
        let r = c.post_multipart(&frames, &parts);
        assert_eq!((r.status, r.code()), (400, "bad_request".into()));
        assert!(
            r.message().contains(&format!(
                "unknown part `{extra}` (expected only `image` parts)"
            )),
            "{}",
            r.message()
        );
    }
    let r = c.post_multipart(&frames, &query_parts(&route, 6..19));
    check("POST", FRAMES, &r);
    assert_eq!((r.status, r.code()), (400, "batch_too_large".into()));
    let r = c.request("POST", &frames, Some("application/json"), b"{}");
    check("POST", FRAMES, &r);
    assert_eq!(r.status, 415);
    assert!(
        r.message()
            .contains("expected `Content-Type: multipart/form-data` with `image` parts, got `application/json`"),
        "{}",
        r.message()
    );
    let r = c.request("POST", &frames, None, b"x");
    assert_eq!(r.status, 415);
    assert!(
        r.message().contains("has no Content-Type"),
        "{}",
        r.message()
    );
    let r = c.request("POST", &frames, Some("multipart/form-data"), b"x");
    assert_eq!(r.status, 415);
    assert!(r.message().contains("boundary"), "{}", r.message());
    assert_eq!(c.get(&format!("/v1/trips/{trip}")).json()["frame_count"], 6);
    let a = post_frames(&c, &trip, &query_parts(&route, 6..12));
    let b = post_frames(&c, &twin, &query_parts(&route, 6..12));
    assert_eq!(answer(&a), answer(&b));
    let (ra, rb) = (
        c.get(&format!("/v1/trips/{trip}")).json(),
        c.get(&format!("/v1/trips/{twin}")).json(),
    );
    assert_eq!(ra["estimates"], rb["estimates"]);
    // Listing parameters.
    for q in ["limit=0", "limit=101", "before=xyz", "color=red"] {
        let r = c.get(&format!("/v1/maps/{map}/trips?{q}"));
        check("GET", OPEN, &r);
        assert_eq!(
            (r.status, r.code()),
            (400, "invalid_parameter".into()),
            "{q}"
        );
    }
    let r = c.get("/v1/maps/00000000000000ff/trips");
    assert_eq!((r.status, r.code()), (404, "map_not_found".into()));
}

#[test]
fn concurrent_trips_do_not_interfere_and_one_trip_stays_ordered() {
    let server = Server::start();
    let c = server.client;
    let route = Route::new(40, 21);
    let map = route_map(&c, &route, 40);
    let trips: Vec<String> = (0..4).map(|_| open(&c, &map, None)).collect();
    let answers: Vec<Vec<Value>> = std::thread::scope(|s| {
        let handles: Vec<_> = trips
            .iter()
            .map(|t| {
                let route = &route;
                s.spawn(move || {
                    (0..3u32)
                        .map(|b| {
                            answer(&post_frames(
                                &c,
                                t,
                                &query_parts(route, b * 10..b * 10 + 10),
                            ))
                        })
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    for a in &answers[1..] {
        assert_eq!(a, &answers[0]);
    }
    // Two clients posting to one trip at once: both batches are applied, one after the other.
    let shared = open(&c, &map, None);
    let frames: Vec<Value> = std::thread::scope(|s| {
        let hs: Vec<_> = (0..2u32)
            .map(|k| {
                let (route, shared) = (&route, &shared);
                s.spawn(move || post_frames(&c, shared, &query_parts(route, k * 5..k * 5 + 5)))
            })
            .collect();
        hs.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let mut firsts: Vec<u64> = frames
        .iter()
        .map(|f| f["estimates"][0]["frame"].as_u64().unwrap())
        .collect();
    firsts.sort_unstable();
    assert_eq!(firsts, vec![0, 5]);
    assert_eq!(
        c.get(&format!("/v1/trips/{shared}")).json()["frame_count"],
        10
    );
}

#[test]
fn a_trip_continues_identically_after_sigkill_and_restart() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, log) = (tmp.path().join("data"), tmp.path().join("serve.log"));
    let route = Route::new(50, 33);
    let batches: Vec<Vec<Part>> = (0..5u32)
        .map(|b| query_parts(&route, b * 8..b * 8 + 8))
        .collect();
    let p = Process::serve(&data, &log);
    let map = route_map(&p.client, &route, 50);
    let trip = open(&p.client, &map, Some(json!({"lag": 12})));
    let mut before = Vec::new();
    for b in &batches[..2] {
        before.push(answer(&post_frames(&p.client, &trip, b)));
    }
    let read_before = p.client.get(&format!("/v1/trips/{trip}")).json();
    p.kill();

    let p = Process::serve(&data, &log);
    let c = p.client;
    assert_eq!(c.get(&format!("/v1/trips/{trip}")).json(), read_before);
    let mut continued = before;
    for b in &batches[2..] {
        continued.push(answer(&post_frames(&c, &trip, b)));
    }
    // An uninterrupted trip over the same frames gives the same answers, batch by batch.
    let fresh = open(&c, &map, Some(json!({"lag": 12})));
    let uninterrupted: Vec<Value> = batches
        .iter()
        .map(|b| answer(&post_frames(&c, &fresh, b)))
        .collect();
    assert_eq!(continued, uninterrupted);
    assert_eq!(
        c.get(&format!("/v1/trips/{trip}")).json()["estimates"],
        c.get(&format!("/v1/trips/{fresh}")).json()["estimates"]
    );
    assert!(p.terminate());
}

/// For F = 1 without relocalization (and raw cosine rows, as the offline `normalize: false`),
/// the estimate a trip reports for its latest frame equals the offline localization of all
/// frames so far, for that frame — on real Nordland frames, after every batch.
#[test]
fn online_latest_estimate_equals_offline_localization_on_nordland() {
    let Some(dir) = nordland() else { return };
    let server = Server::start();
    let c = server.client;
    let summer = nordland_files(&dir.join("summer"));
    let winter = nordland_files(&dir.join("winter"));
    let read = |p: &std::path::PathBuf| std::fs::read(p).unwrap();
    let map = create_hog_map(&c, "nordland-summer", 8);
    for chunk in summer[..600].chunks(200) {
        let parts: Vec<Part> = chunk
            .iter()
            .map(|p| Part::image(&p.file_name().unwrap().to_string_lossy(), read(p)))
            .collect();
        let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &parts);
        assert_eq!(r.status, 200, "{}", body(&r));
    }
    let w = 1.6;
    let trip = open(
        &c,
        &map,
        Some(json!({"normalize": false, "relocalization": false, "hidden_cost": w, "lag": 16})),
    );
    let part =
        |p: &std::path::PathBuf| Part::image(&p.file_name().unwrap().to_string_lossy(), read(p));
    let queries: Vec<Part> = winter[..150].iter().map(part).collect();
    let mut compared = 0;
    for end in (10..=150).step_by(10) {
        let v = post_frames(&c, &trip, &queries[end - 10..end]);
        let online = v["estimates"][9]["ref"].clone();
        let mut parts: Vec<Part> = winter[..end].iter().map(part).collect();
        parts.push(Part::json(
            "params",
            &json!({"normalize": false, "hidden_cost": w, "flows": 1}),
        ));
        let r = c.post_multipart(&format!("/v1/maps/{map}/localize"), &parts);
        assert_eq!(r.status, 200, "{}", body(&r));
        let offline = r.json()["predictions"]
            .as_array()
            .unwrap()
            .iter()
            .find(|p| p["query"] == end - 1)
            .map_or(Value::Null, |p| p["ref"].clone());
        assert_eq!(online, offline, "latest frame {}", end - 1);
        compared += 1;
    }
    assert_eq!(compared, 15);
}
