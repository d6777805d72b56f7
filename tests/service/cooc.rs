//! Co-occurrence maps over HTTP on generated images: create, build from the first batch, add a
//! further drive, localize with each method; every error stores nothing; a restart keeps the
//! map (and its drives).

use serde_json::{json, Value};

use crate::common::{create_hog_map, within_one_frame, Process, Route, Server};
use crate::http::{Client, Part};
use crate::spec::check;

fn create_cooc(c: &Client) -> String {
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": "cooc", "descriptor": {"kind": "cooc", "vocabulary_branching": 8}}),
    );
    check("post", "/v1/maps", &r);
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let m = r.json();
    let d = &m["descriptor"];
    assert_eq!(d["kind"], "cooc");
    assert_eq!(d["vocabulary_branching"], 8);
    assert_eq!(d["vocabulary_depth"], 2);
    assert_eq!(d["grid"], json!([12, 8]));
    m["id"].as_str().unwrap().to_string()
}

fn parts(pngs: &[Vec<u8>], json_part: Option<(&str, Value)>) -> Vec<Part> {
    let mut p: Vec<Part> = pngs
        .iter()
        .enumerate()
        .map(|(i, b)| Part::image(&format!("f{i}.png"), b.clone()))
        .collect();
    if let Some((name, v)) = json_part {
        p.push(Part::json(name, &v));
    }
    p
}

fn drive(c: &Client, map: &str, pngs: &[Vec<u8>], d: Value) -> crate::http::Response {
    let r = c.post_multipart(
        &format!("/v1/maps/{map}/drives"),
        &parts(pngs, Some(("drive", d))),
    );
    check("post", "/v1/maps/{id}/drives", &r);
    r
}

fn localize(c: &Client, map: &str, pngs: &[Vec<u8>], params: Value) -> Value {
    let r = c.post_multipart(
        &format!("/v1/maps/{map}/localize"),
        &parts(pngs, Some(("params", params))),
    );
    check("post", "/v1/maps/{id}/localize", &r);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    r.json()
}

/// Predictions within one frame of the truth (query k shows location `first + k`).
fn correct(result: &Value, first: i64) -> usize {
    result["predictions"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| (p["ref"].as_i64().unwrap() - p["query"].as_i64().unwrap() - first).abs() <= 1)
        .count()
}

#[test]
fn cooc_map_builds_adds_a_drive_and_localizes_with_each_method() {
    let server = Server::start();
    let c = &server.client;
    let route = Route::new(30, 21);
    let refs: Vec<Vec<u8>> = (0..30).map(|i| route.reference_png(i)).collect();
    let night: Vec<Vec<u8>> = (0..30).map(|i| route.query_png(i)).collect();
    let map = create_cooc(c);

    // Nothing to localize against or add to yet.
    let r = drive(c, &map, &night[..2], json!({"locations": [0, 1]}));
    assert_eq!((r.status, r.code()), (409, "map_empty".into()));
    let r = c.post_multipart(
        &format!("/v1/maps/{map}/localize"),
        &parts(&night[..3], None),
    );
    assert_eq!((r.status, r.code()), (409, "map_empty".into()));

    // The first batch is the first drive: the map is built from it.
    let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &parts(&refs, None));
    check("post", "/v1/maps/{id}/images", &r);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["image_count"], 30);
    let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &parts(&refs[..2], None));
    assert_eq!((r.status, r.code()), (409, "map_kind".into()));
    assert!(r.message().contains("/drives"), "{}", r.message());

    // Bad drives store nothing.
    // Valid by the schema, but not fitting the map (30 locations) or the images (two).
    let r = drive(c, &map, &night[..2], json!({"locations": [0, 30]}));
    assert_eq!((r.status, r.code()), (422, "inconsistent_parameter".into()));
    assert!(
        r.message().contains("drive.locations[1]"),
        "{}",
        r.message()
    );
    let r = drive(c, &map, &night[..2], json!({"locations": [0]}));
    assert_eq!((r.status, r.code()), (422, "inconsistent_parameter".into()));
    let r = c.post_multipart(&format!("/v1/maps/{map}/drives"), &parts(&night[..2], None));
    assert_eq!((r.status, r.code()), (400, "invalid_parameter".into()));
    let mut broken = night[..2].to_vec();
    broken[1] = b"not an image".to_vec();
    let r = drive(c, &map, &broken, json!({"locations": [0, 1]}));
    assert_eq!((r.status, r.code()), (422, "invalid_image".into()));
    let r = drive(c, &map, &[], json!({"locations": []}));
    assert_eq!(r.status, 400, "{}", String::from_utf8_lossy(&r.body));

    // Before the night drive: the flow graph on co-occurrence scores.
    let queries: Vec<Vec<u8>> = (5..25).map(|i| route.query_png(i)).collect();
    let flow = localize(c, &map, &queries, json!({}));
    assert_eq!(flow["params"]["method"], "flow");
    assert!(!flow["hypotheses"].as_array().unwrap().is_empty());
    assert_eq!(flow["reference_count"], 30);

    // A night drive of every location (odd frames in reverse order, to exercise the indices).
    let order: Vec<u32> = (0..30).rev().collect();
    let pngs: Vec<Vec<u8>> = order.iter().map(|&i| night[i as usize].clone()).collect();
    let r = drive(c, &map, &pngs, json!({"locations": order, "time": 22.0}));
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json(), json!({"drives": 2, "images": 30}));
    assert_eq!(c.get(&format!("/v1/maps/{map}")).json()["image_count"], 30);

    for method in ["flow", "cooc", "cooc-seq"] {
        let result = localize(c, &map, &queries, json!({"method": method}));
        assert_eq!(result["params"]["method"], method);
        assert_eq!(result["query_count"], 20);
        let hyps = result["hypotheses"].as_array().unwrap();
        assert_eq!(hyps.is_empty(), method != "flow", "{method}");
        // The night appearance is now in the map: most queries are found.
        let ok = correct(&result, 5);
        assert!(ok >= 14, "{method}: {ok} of 20 correct: {result}");
        let id = result["id"].as_str().unwrap();
        assert_eq!(c.get(&format!("/v1/localizations/{id}")).json(), result);
    }

    // Wrong kinds of requests.
    let r = c.post_json(
        &format!("/v1/maps/{map}/descriptors"),
        &json!({"descriptors": [[1.0]]}),
    );
    assert_eq!((r.status, r.code()), (409, "map_kind".into()));
    let r = c.post_json(
        &format!("/v1/maps/{map}/localize"),
        &json!({"descriptors": [[1.0]]}),
    );
    assert_eq!((r.status, r.code()), (409, "map_kind".into()));
    let hog = create_hog_map(c, "hog", 8);
    let r = drive(c, &hog, &night[..1], json!({"locations": [0]}));
    assert_eq!((r.status, r.code()), (409, "map_kind".into()));
    let r = c.post_multipart(&format!("/v1/maps/{hog}/images"), &parts(&refs[..4], None));
    assert_eq!(r.status, 200);
    let r = c.post_multipart(
        &format!("/v1/maps/{hog}/localize"),
        &parts(&queries[..2], Some(("params", json!({"method": "cooc"})))),
    );
    assert_eq!((r.status, r.code()), (409, "map_kind".into()));
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": "x", "descriptor": {"kind": "cooc", "vocabulary_branching": 1}}),
    );
    assert_eq!((r.status, r.code()), (400, "invalid_parameter".into()));
    assert!(
        r.message().contains("descriptor.vocabulary_branching"),
        "{}",
        r.message()
    );
}

#[test]
fn a_restart_keeps_the_cooc_map_and_its_drives() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let log = tmp.path().join("serve.log");
    let route = Route::new(20, 4);
    let refs: Vec<Vec<u8>> = (0..20).map(|i| route.reference_png(i)).collect();
    let queries: Vec<Vec<u8>> = (3..15).map(|i| route.query_png(i)).collect();

    let p = Process::serve(&data, &log);
    let map = create_cooc(&p.client);
    let r = p
        .client
        .post_multipart(&format!("/v1/maps/{map}/images"), &parts(&refs, None));
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let r = drive(
        &p.client,
        &map,
        &queries[..4],
        json!({"locations": [3, 4, 5, 6]}),
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let before = localize(&p.client, &map, &queries, json!({"method": "cooc"}));
    assert!(p.terminate());

    let p = Process::serve(&data, &log);
    let after = localize(&p.client, &map, &queries, json!({"method": "cooc"}));
    assert_eq!(after["predictions"], before["predictions"]);
    let r = drive(
        &p.client,
        &map,
        &queries[4..6],
        json!({"locations": [7, 8]}),
    );
    assert_eq!(
        r.json()["drives"],
        3,
        "the drive before the restart is still there"
    );
    assert!(p.terminate());
}

/// Predictions of a `--predictions` CSV: `(query, ref, confidence)` per row.
fn csv_predictions(path: &std::path::Path) -> Vec<(i64, i64, f64)> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (
                f[0].parse().unwrap(),
                f[1].parse().unwrap(),
                f[2].parse().unwrap(),
            )
        })
        .collect()
}

/// A map fused over HTTP (first `/images` batch, then `POST /drives` with a time) is the map
/// `seasonloc eval` fuses from the same drives (`--reference` twice with `--reference-time`):
/// both answer every query with the same location and confidence, for `cooc` and `cooc-seq`.
#[test]
fn drives_over_http_fuse_the_same_map_as_eval() {
    let server = Server::start();
    let c = &server.client;
    let route = Route::new(30, 13);
    let refs: Vec<Vec<u8>> = (0..30).map(|i| route.reference_png(i)).collect();
    let night: Vec<Vec<u8>> = (0..30).map(|i| route.query_png(i)).collect();
    // Queries: a third appearance of locations 4..26 (the night frames brightened).
    let queries: Vec<Vec<u8>> = (4..26)
        .map(|i| {
            let mut img = image::load_from_memory(&night[i]).unwrap().to_luma8();
            for p in img.pixels_mut() {
                p.0[0] = p.0[0].saturating_add(25);
            }
            crate::common::png(&img)
        })
        .collect();
    let tmp = tempfile::tempdir().unwrap();
    let write = |name: &str, pngs: &[Vec<u8>]| -> String {
        let dir = tmp.path().join(name);
        std::fs::create_dir_all(&dir).unwrap();
        for (i, b) in pngs.iter().enumerate() {
            std::fs::write(dir.join(format!("f{i:03}.png")), b).unwrap();
        }
        dir.to_str().unwrap().to_string()
    };
    let (day_dir, night_dir, query_dir) = (
        write("day", &refs),
        write("night", &night),
        write("query", &queries),
    );
    let gt = tmp.path().join("gt.csv");
    let rows: String = (0..22).map(|q| format!("{q},{}\n", q + 4)).collect();
    std::fs::write(&gt, format!("query_index,ref_index\n{rows}")).unwrap();

    // The service: the day drive builds the map, the night drive (time 22) is fused into it.
    let map = create_cooc(c);
    let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &parts(&refs, None));
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let locations: Vec<u32> = (0..30).collect();
    let r = drive(
        c,
        &map,
        &night,
        json!({"locations": locations, "time": 22.0}),
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));

    for method in ["cooc", "cooc-seq"] {
        let preds = tmp.path().join(format!("{method}.csv"));
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_seasonloc"))
            .args(["eval", "--reference", &day_dir, "--reference", &night_dir])
            .args(["--reference-time", "0", "--reference-time", "22"])
            .args([
                "--query",
                &query_dir,
                "--ground-truth",
                gt.to_str().unwrap(),
            ])
            .args(["--method", method, "--cooc-branching", "8"])
            .args(["--predictions", preds.to_str().unwrap()])
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let offline = csv_predictions(&preds);
        let online = localize(c, &map, &queries, json!({"method": method}));
        let online: Vec<(i64, i64, f64)> = online["predictions"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| {
                (
                    p["query"].as_i64().unwrap(),
                    p["ref"].as_i64().unwrap(),
                    p["confidence"].as_f64().unwrap(),
                )
            })
            .collect();
        assert_eq!(offline.len(), online.len(), "{method}");
        assert!(offline.len() >= 20, "{method}: {offline:?}");
        for (a, b) in offline.iter().zip(&online) {
            assert_eq!(
                (a.0, a.1),
                (b.0, b.1),
                "{method}: eval {a:?}, service {b:?}"
            );
            assert!(
                (a.2 - b.2).abs() <= 1e-4 * a.2.abs().max(1.0),
                "{method}: {a:?} {b:?}"
            );
        }
        // Not a vacuous agreement: the fused map finds most queries.
        let found = online.iter().filter(|p| (p.1 - p.0 - 4).abs() <= 1).count();
        assert!(found >= 15, "{method}: {found} of 22 found: {online:?}");
    }
}

/// The latest estimates and status of a batch (what two identical trips must agree on).
fn trip_answer(v: &Value) -> Value {
    json!({"estimates": v["estimates"], "status": v["status"], "window": v["window"],
           "hidden_cost": v["hidden_cost"], "frame_count": v["frame_count"]})
}

fn post_frames(c: &Client, trip: &str, pngs: &[Vec<u8>]) -> Value {
    let r = c.post_multipart(&format!("/v1/trips/{trip}/frames"), &parts(pngs, None));
    check("POST", "/v1/trips/{id}/frames", &r);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    r.json()
}

fn open_trip(c: &Client, map: &str) -> String {
    let r = c.post_json(&format!("/v1/maps/{map}/trips"), &json!({"lag": 12}));
    check("POST", "/v1/maps/{id}/trips", &r);
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    r.json()["id"].as_str().unwrap().to_string()
}

/// A trip on a co-occurrence map: each frame's score row feeds the same online graph as a HOG
/// trip (estimates, status, confidence), and after SIGKILL and a restart it continues exactly
/// as an uninterrupted trip over the same frames.
#[test]
fn a_trip_on_a_cooc_map_localizes_and_continues_after_sigkill() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let log = tmp.path().join("serve.log");
    let route = Route::new(40, 8);
    let refs: Vec<Vec<u8>> = (0..40).map(|i| route.reference_png(i)).collect();
    let batches: Vec<Vec<Vec<u8>>> = (0..4u32)
        .map(|b| (b * 8..b * 8 + 8).map(|i| route.query_png(i)).collect())
        .collect();

    let p = Process::serve(&data, &log);
    let map = create_cooc(&p.client);
    let empty = open_trip_status(&p.client, &map);
    assert_eq!(empty, (409, "map_empty".into()));
    let r = p
        .client
        .post_multipart(&format!("/v1/maps/{map}/images"), &parts(&refs, None));
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let trip = open_trip(&p.client, &map);
    let mut before = Vec::new();
    for b in &batches[..2] {
        let v = post_frames(&p.client, &trip, b);
        assert_eq!(v["estimates"].as_array().unwrap().len(), 8);
        before.push(trip_answer(&v));
    }
    let read_before = p.client.get(&format!("/v1/trips/{trip}")).json();
    assert_eq!(read_before["frame_count"], 16);
    assert_eq!(read_before["reference_count"], 40);
    p.kill();

    let p = Process::serve(&data, &log);
    let c = &p.client;
    assert_eq!(c.get(&format!("/v1/trips/{trip}")).json(), read_before);
    let mut continued = before;
    let mut last = Value::Null;
    for b in &batches[2..] {
        last = post_frames(c, &trip, b);
        continued.push(trip_answer(&last));
    }
    // The route is distinctive: the trip is localized and the latest frame found.
    assert_eq!(last["status"], "localized", "{last}");
    let latest = &last["estimates"][7];
    let j = latest["ref"]
        .as_i64()
        .expect("the last frame is on the map");
    assert!((j - 31).abs() <= 1, "{latest}");
    assert!(latest["confidence"].as_f64().unwrap() > 1.0, "{latest}");
    let t = c.get(&format!("/v1/trips/{trip}")).json();
    let est = t["estimates"].as_array().unwrap();
    assert_eq!(est.len(), 32);
    let correct = within_one_frame(est);
    assert!(
        correct >= 26,
        "{correct} of 32 frames within one frame: {t}"
    );
    // An uninterrupted trip over the same frames answers the same, batch by batch.
    let fresh = open_trip(c, &map);
    let uninterrupted: Vec<Value> = batches
        .iter()
        .map(|b| trip_answer(&post_frames(c, &fresh, b)))
        .collect();
    assert_eq!(continued, uninterrupted);
    assert!(p.terminate());
}

fn open_trip_status(c: &Client, map: &str) -> (u16, String) {
    let r = c.post_json(&format!("/v1/maps/{map}/trips"), &json!({}));
    check("POST", "/v1/maps/{id}/trips", &r);
    (r.status, r.code())
}
