//! The whole flow over HTTP: create a map, upload reference images in batches, localize a query
//! sequence, read the result back and list it; on generated images and on real Nordland frames.
//! The HTTP result must equal the library's for the same images and parameters.

use serde_json::{json, Value};

use seasonloc_core::features::hog::{HogOptions, HogSpec};
use seasonloc_core::localize::{localize, LocalizeOptions};
use seasonloc_core::solver::{HiddenCost, SolverParams};

use crate::common::{create_hog_map, library_descriptors, nordland, nordland_files, Route, Server};
use crate::http::{Client, Part};
use crate::spec::check;

/// The library's answer for the same encoded images and options.
fn library(
    refs: &[Vec<u8>],
    queries: &[Vec<u8>],
    cell_size: u32,
    options: &LocalizeOptions,
) -> seasonloc_core::localize::Localization {
    let spec = HogSpec::new(HogOptions {
        cell_size,
        resize: None,
    })
    .unwrap();
    localize(
        &library_descriptors(&spec, queries),
        &library_descriptors(&spec, refs),
        options,
    )
    .unwrap()
}

fn assert_same_as_library(http: &Value, lib: &seasonloc_core::localize::Localization) {
    let preds = http["predictions"].as_array().unwrap();
    assert_eq!(preds.len(), lib.predictions.len());
    for (h, l) in preds.iter().zip(&lib.predictions) {
        assert_eq!(h["query"].as_u64().unwrap() as usize, l.query);
        assert_eq!(h["ref"].as_u64().unwrap() as usize, l.reference);
        assert_eq!(h["confidence"].as_f64().unwrap(), l.confidence);
    }
    let hyps = http["hypotheses"].as_array().unwrap();
    assert_eq!(hyps.len(), lib.solution.hypotheses.len());
    for (h, l) in hyps.iter().zip(&lib.solution.hypotheses) {
        assert_eq!(h["rank"].as_u64().unwrap() as usize, l.rank);
        assert_eq!(h["cost"].as_f64().unwrap(), l.cost);
        let rows = h["rows"].as_array().unwrap();
        assert_eq!(rows.len(), l.rows.len());
        for (hr, lr) in rows.iter().zip(&l.rows) {
            assert_eq!(hr["query"].as_u64().unwrap() as usize, lr.query);
            let refs: Vec<usize> = hr["matches"]
                .as_array()
                .unwrap()
                .iter()
                .map(|m| m["ref"].as_u64().unwrap() as usize)
                .collect();
            let lrefs: Vec<usize> = lr.matches.iter().map(|m| m.reference).collect();
            assert_eq!(refs, lrefs);
        }
    }
    assert_eq!(
        http["params"]["hidden_cost"].as_f64().unwrap(),
        lib.solution.hidden_cost
    );
}

fn upload(c: &Client, map: &str, images: &[(String, Vec<u8>)], metadata: Option<Value>) -> Value {
    let mut parts: Vec<Part> = images
        .iter()
        .map(|(name, bytes)| Part::image(name, bytes.clone()))
        .collect();
    if let Some(m) = metadata {
        parts.push(Part::json("metadata", &m));
    }
    let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &parts);
    check("post", "/v1/maps/{id}/images", &r);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    r.json()
}

fn run_localize(c: &Client, map: &str, queries: &[(String, Vec<u8>)], params: &Value) -> Value {
    let mut parts: Vec<Part> = queries
        .iter()
        .map(|(name, bytes)| Part::image(name, bytes.clone()))
        .collect();
    parts.push(Part::json("params", params));
    let r = c.post_multipart(&format!("/v1/maps/{map}/localize"), &parts);
    check("post", "/v1/maps/{id}/localize", &r);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    r.json()
}

/// PNG bytes of `png` resized to `w x h` (another camera).
fn rescaled(png: &[u8], (w, h): (u32, u32)) -> Vec<u8> {
    let img = image::load_from_memory(png).unwrap().to_luma8();
    let out = image::imageops::resize(&img, w, h, image::imageops::FilterType::Triangle);
    crate::common::png(&out)
}

/// A HOG map without `resize` takes its input geometry from its first image; query images and
/// trip frames of another size and aspect ratio are then brought to it (stretched), and still
/// localize; the geometry is visible on the map and survives later appends.
#[test]
fn images_of_any_size_are_brought_to_the_map_geometry() {
    let server = Server::start();
    let c = server.client;
    let route = Route::new(60, 11);
    let map = create_hog_map(&c, "any-size", 8);
    let r = c.get(&format!("/v1/maps/{map}"));
    assert_eq!(r.json()["descriptor"]["resize"], Value::Null);
    let refs: Vec<(String, Vec<u8>)> = (0..60)
        .map(|i| (format!("ref-{i:03}.png"), route.reference_png(i)))
        .collect();
    upload(&c, &map, &refs[..30], None);
    // Later reference batches may come from another camera too.
    let bigger: Vec<(String, Vec<u8>)> = refs[30..]
        .iter()
        .map(|(n, b)| (n.clone(), rescaled(b, (128, 64))))
        .collect();
    upload(&c, &map, &bigger, None);
    let r = c.get(&format!("/v1/maps/{map}"));
    check("get", "/v1/maps/{id}", &r);
    assert_eq!(r.json()["descriptor"]["resize"], json!([64, 32]));
    assert_eq!(r.json()["image_count"], 60);

    let correct = |result: &Value, offset: i64| {
        result["predictions"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|p| {
                let q = p["query"].as_i64().unwrap() + offset;
                (p["ref"].as_i64().unwrap() - q).abs() <= 1
            })
            .count()
    };
    for size in [(128, 64), (96, 40), (48, 24)] {
        let queries: Vec<(String, Vec<u8>)> = (10..50)
            .map(|i| (format!("q-{i:03}.png"), rescaled(&route.query_png(i), size)))
            .collect();
        let result = run_localize(&c, &map, &queries, &json!({}));
        let n = correct(&result, 10);
        assert!(n * 10 >= 40 * 8, "{size:?}: only {n} of 40 localized");
    }

    // A trip on the map takes frames of another size as well.
    let r = c.post_json(&format!("/v1/maps/{map}/trips"), &json!({}));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let trip = r.json()["id"].as_str().unwrap().to_string();
    let frames: Vec<Part> = (0..20)
        .map(|i| {
            Part::image(
                &format!("f{i}.png"),
                rescaled(&route.query_png(i), (96, 48)),
            )
        })
        .collect();
    let r = c.post_multipart(&format!("/v1/trips/{trip}/frames"), &frames);
    check("post", "/v1/trips/{id}/frames", &r);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let estimates = r.json()["estimates"].as_array().unwrap().clone();
    assert_eq!(estimates.len(), 20);
    let on_track = estimates
        .iter()
        .filter(|e| {
            let (f, j) = (e["frame"].as_i64().unwrap(), e["ref"].as_i64());
            j.is_some_and(|j| (j - f).abs() <= 1)
        })
        .count();
    assert!(on_track >= 16, "only {on_track} of 20 trip frames on track");
}

/// A camera mounted on its side (or a phone) tags its frames with an Exif orientation instead of
/// rotating their pixels: such query images are turned upright before they are described, so
/// they localize like upright ones (stored a quarter turn anticlockwise, tagged 6: "turn a
/// quarter clockwise to show"), and the map's reference thumbnails show them upright.
#[test]
fn images_tagged_with_an_exif_orientation_are_turned_upright() {
    use image::codecs::png::PngEncoder;
    use image::{ExtendedColorType, ImageEncoder};
    // A little-endian TIFF block whose one IFD entry is Orientation = 6.
    let exif: Vec<u8> = [
        &b"II*\0\x08\0\0\0\x01\0"[..],
        &[0x12, 0x01, 3, 0, 1, 0, 0, 0, 6, 0, 0, 0],
        &[0, 0, 0, 0],
    ]
    .concat();
    let tagged = |png: &[u8]| {
        let img = image::load_from_memory(png).unwrap().to_luma8();
        let stored = image::imageops::rotate270(&img);
        let mut out = Vec::new();
        let mut encoder = PngEncoder::new(&mut out);
        encoder.set_exif_metadata(exif.clone()).unwrap();
        encoder
            .write_image(
                stored.as_raw(),
                stored.width(),
                stored.height(),
                ExtendedColorType::L8,
            )
            .unwrap();
        out
    };
    let server = Server::start();
    let c = server.client;
    let route = Route::new(60, 13);
    let map = create_hog_map(&c, "exif", 8);
    let refs: Vec<(String, Vec<u8>)> = (0..60)
        .map(|i| (format!("ref-{i:03}.png"), route.reference_png(i)))
        .collect();
    upload(&c, &map, &refs, None);
    let queries: Vec<(String, Vec<u8>)> = (10..50)
        .map(|i| (format!("q-{i:03}.png"), tagged(&route.query_png(i))))
        .collect();
    let result = run_localize(&c, &map, &queries, &json!({}));
    let n = result["predictions"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| (p["ref"].as_i64().unwrap() - p["query"].as_i64().unwrap() - 10).abs() <= 1)
        .count();
    assert!(n * 10 >= 40 * 8, "only {n} of 40 tagged queries localized");

    // A map whose first image is tagged takes the upright size as its geometry.
    let upright = create_hog_map(&c, "exif-first", 8);
    upload(&c, &upright, &[("r.png".into(), tagged(&refs[0].1))], None);
    let r = c.get(&format!("/v1/maps/{upright}"));
    assert_eq!(r.json()["descriptor"]["resize"], json!([64, 32]));
}

/// The case: a map built from 960x540 frames takes 640x360 query images and trip frames
/// (another camera, same aspect ratio) without any per-request setting, and localizes them.
#[test]
fn a_960x540_map_takes_640x360_queries_and_trip_frames() {
    let server = Server::start();
    let c = server.client;
    let route = Route::new(50, 23);
    // 32 px cells on 960x540 see about the detail 2 px cells see on the 64x32 originals.
    let map = create_hog_map(&c, "hd", 32);
    let refs: Vec<(String, Vec<u8>)> = (0..50)
        .map(|i| {
            (
                format!("ref-{i:03}.png"),
                rescaled(&route.reference_png(i), (960, 540)),
            )
        })
        .collect();
    upload(&c, &map, &refs, None);
    let r = c.get(&format!("/v1/maps/{map}"));
    assert_eq!(r.json()["descriptor"]["resize"], json!([960, 540]));
    let queries: Vec<(String, Vec<u8>)> = (5..45)
        .map(|i| {
            (
                format!("q-{i:03}.png"),
                rescaled(&route.query_png(i), (640, 360)),
            )
        })
        .collect();
    let result = run_localize(&c, &map, &queries, &json!({}));
    let preds = result["predictions"].as_array().unwrap();
    let correct = preds
        .iter()
        .filter(|p| {
            let q = p["query"].as_i64().unwrap() + 5;
            (p["ref"].as_i64().unwrap() - q).abs() <= 1
        })
        .count();
    assert!(
        correct >= 32,
        "only {correct} of 40 640x360 queries localized: {result}"
    );

    let r = c.post_json(&format!("/v1/maps/{map}/trips"), &json!({}));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let trip = r.json()["id"].as_str().unwrap().to_string();
    let mut on_track = 0;
    for b in 0..3 {
        let frames: Vec<Part> = (b * 10..b * 10 + 10)
            .map(|i| {
                Part::image(
                    &format!("f{i}.png"),
                    rescaled(&route.query_png(i), (640, 360)),
                )
            })
            .collect();
        let r = c.post_multipart(&format!("/v1/trips/{trip}/frames"), &frames);
        check("post", "/v1/trips/{id}/frames", &r);
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        for e in r.json()["estimates"].as_array().unwrap() {
            let (f, j) = (e["frame"].as_i64().unwrap(), e["ref"].as_i64());
            on_track += usize::from(j.is_some_and(|j| (j - f).abs() <= 1));
        }
    }
    assert!(
        on_track >= 24,
        "only {on_track} of 30 640x360 trip frames on track"
    );
    // A frame too small to hold one HOG cell is still a clear error.
    let tiny = rescaled(&route.query_png(0), (20, 12));
    let r = c.post_multipart(
        &format!("/v1/trips/{trip}/frames"),
        &[Part::image("tiny.png", tiny)],
    );
    assert_eq!(r.status, 422, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["error"]["code"], "invalid_image");
}

#[test]
fn generated_route_end_to_end() {
    let server = Server::start();
    let c = server.client;
    let route = Route::new(60, 7);
    let refs: Vec<(String, Vec<u8>)> = (0..60)
        .map(|i| (format!("ref-{i:03}.png"), route.reference_png(i)))
        .collect();
    let queries: Vec<(String, Vec<u8>)> = (10..40)
        .map(|i| (format!("query-{i:03}.png"), route.query_png(i)))
        .collect();

    let map = create_hog_map(&c, "generated", 8);
    let meta: Vec<Value> = (0..25)
        .map(|i| json!({"timestamp": format!("2024-01-01T00:00:{i:02}Z"), "latitude": 63.4, "longitude": 10.4, "label": format!("km {i}")}))
        .collect();
    let first = upload(&c, &map, &refs[..25], Some(Value::Array(meta)));
    assert_eq!(first["indices"], json!((0..25).collect::<Vec<u32>>()));
    let second = upload(&c, &map, &refs[25..], None);
    assert_eq!(second["indices"][0], 25);
    assert_eq!(second["image_count"], 60);

    let r = c.get(&format!("/v1/maps/{map}"));
    check("get", "/v1/maps/{id}", &r);
    assert_eq!(r.json()["image_count"], 60);
    let r = c.get("/v1/maps");
    check("get", "/v1/maps", &r);
    assert!(r.json()["maps"]
        .as_array()
        .unwrap()
        .iter()
        .any(|m| m["id"] == map.as_str()));

    let params =
        json!({"fan_out": 4, "hidden_cost": 1.3, "flows": 2, "exact": false, "horizontal": true});
    let result = run_localize(&c, &map, &queries, &params);
    assert_eq!(result["query_count"], 30);
    assert_eq!(result["reference_count"], 60);
    assert_eq!(result["hypotheses"].as_array().unwrap().len(), 2);
    let preds = result["predictions"].as_array().unwrap();
    let correct = preds
        .iter()
        .filter(|p| {
            let q = p["query"].as_i64().unwrap() + 10;
            (p["ref"].as_i64().unwrap() - q).abs() <= 1
        })
        .count();
    assert!(
        correct * 10 >= queries.len() * 8,
        "only {correct} of {} queries localized",
        queries.len()
    );
    // Every prediction of the flow method carries its calibrated probability; the right ones
    // are, on this easy route, likely by it.
    for p in preds {
        let pc = p["p_correct"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&pc), "{p}");
    }
    let mean_p: f64 = preds
        .iter()
        .map(|p| p["p_correct"].as_f64().unwrap())
        .sum::<f64>()
        / preds.len() as f64;
    assert!(mean_p > 0.5, "mean p_correct {mean_p}");

    let options = LocalizeOptions {
        solver: SolverParams {
            fan_out: 4,
            hidden_cost: HiddenCost::Fixed(1.3),
            flows: 2,
            exact: false,
            horizontal: true,
            stop_hidden_fraction: None,
        },
        normalization: seasonloc_core::similarity::Normalization::default(),
        ..Default::default()
    };
    let ref_bytes: Vec<Vec<u8>> = refs.iter().map(|(_, b)| b.clone()).collect();
    let query_bytes: Vec<Vec<u8>> = queries.iter().map(|(_, b)| b.clone()).collect();
    assert_same_as_library(&result, &library(&ref_bytes, &query_bytes, 8, &options));

    // Read back: identical document; listed newest first.
    let id = result["id"].as_str().unwrap();
    let back = c.get(&format!("/v1/localizations/{id}"));
    check("get", "/v1/localizations/{id}", &back);
    assert_eq!(back.json(), result);
    let again = run_localize(&c, &map, &queries[..10], &json!({}));
    assert_eq!(again["params"]["hidden_cost_mode"], "auto");
    let list = c.get(&format!("/v1/localizations?map={map}&limit=1"));
    check("get", "/v1/localizations", &list);
    let page = list.json();
    assert_eq!(page["items"][0]["id"], again["id"]);
    let next = page["next"].as_str().unwrap();
    let page2 = c
        .get(&format!(
            "/v1/localizations?map={map}&limit=1&before={next}"
        ))
        .json();
    assert_eq!(page2["items"][0]["id"], result["id"]);
    assert_eq!(page2["next"], Value::Null);

    // Metrics saw the work.
    let metrics = String::from_utf8(c.get("/metrics").body).unwrap();
    assert!(
        metrics.contains("seasonloc_images_ingested_total 60"),
        "{metrics}"
    );
    assert!(
        metrics.contains("seasonloc_queries_localized_total 40"),
        "{metrics}"
    );
    assert!(
        metrics.contains("route=\"/v1/maps/{id}/localize\",status=\"200\"} 2"),
        "{metrics}"
    );
    assert!(
        metrics.contains("seasonloc_stage_duration_seconds_count{stage=\"solve\"} 2"),
        "{metrics}"
    );

    // A wider tolerance makes the same predictions likelier, and is reported with the result.
    let wide = run_localize(
        &c,
        &map,
        &queries,
        &json!({"fan_out": 4, "hidden_cost": 1.3, "flows": 2, "tolerance": 3}),
    );
    assert_eq!(wide["params"]["tolerance"], 3);
    assert!(
        result["params"].get("tolerance").is_none(),
        "the default tolerance is not stated"
    );
    for (a, b) in preds.iter().zip(wide["predictions"].as_array().unwrap()) {
        assert_eq!((&a["query"], &a["ref"]), (&b["query"], &b["ref"]));
        assert!(
            b["p_correct"].as_f64().unwrap() >= a["p_correct"].as_f64().unwrap(),
            "{a} {b}"
        );
    }

    // Deleting the map deletes its results.
    let r = c.delete(&format!("/v1/maps/{map}"));
    check("delete", "/v1/maps/{id}", &r);
    assert_eq!(r.status, 204);
    let r = c.get(&format!("/v1/localizations/{id}"));
    check("get", "/v1/localizations/{id}", &r);
    assert_eq!(r.code(), "localization_not_found");
}

#[test]
fn precomputed_descriptors_end_to_end() {
    let server = Server::start();
    let c = server.client;
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": "own", "descriptor": {"kind": "precomputed", "dim": 3}}),
    );
    check("post", "/v1/maps", &r);
    let map = r.json()["id"].as_str().unwrap().to_string();
    // A route whose descriptors rotate slowly; queries are noisy copies of references 4..12.
    let desc = |i: usize, noise: f64| -> Vec<f64> {
        let a = i as f64 * 0.35;
        vec![a.cos() + noise, a.sin() - noise, 0.5 + 0.1 * (i % 3) as f64]
    };
    let refs: Vec<Vec<f64>> = (0..20).map(|i| desc(i, 0.0)).collect();
    let r = c.post_json(
        &format!("/v1/maps/{map}/descriptors"),
        &json!({"descriptors": refs[..12]}),
    );
    check("post", "/v1/maps/{id}/descriptors", &r);
    assert_eq!(r.json()["image_count"], 12);
    let raw: Vec<u8> = refs[12..]
        .iter()
        .flatten()
        .flat_map(|v| (*v as f32).to_le_bytes())
        .collect();
    let r = c.request(
        "POST",
        &format!("/v1/maps/{map}/descriptors"),
        Some("application/octet-stream"),
        &raw,
    );
    check("post", "/v1/maps/{id}/descriptors", &r);
    assert_eq!(r.json()["indices"], json!((12..20).collect::<Vec<u32>>()));

    let queries: Vec<Vec<f64>> = (4..12).map(|i| desc(i, 0.01)).collect();
    let params = json!({"fan_out": 3, "hidden_cost": "auto", "normalize": false});
    let r = c.post_json(
        &format!("/v1/maps/{map}/localize"),
        &json!({"descriptors": queries, "params": params}),
    );
    check("post", "/v1/maps/{id}/localize", &r);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let http = r.json();

    let to_matrix = |rows: &[Vec<f64>]| {
        let f: Vec<Vec<f32>> = rows
            .iter()
            .map(|r| r.iter().map(|v| *v as f32).collect())
            .collect();
        seasonloc_core::Matrix::from_rows(&f).unwrap()
    };
    let options = LocalizeOptions {
        solver: SolverParams {
            fan_out: 3,
            ..SolverParams::default()
        },
        normalization: seasonloc_core::similarity::Normalization::None,
        ..Default::default()
    };
    let lib = localize(&to_matrix(&queries), &to_matrix(&refs), &options).unwrap();
    assert_same_as_library(&http, &lib);
}

#[test]
fn nordland_end_to_end() {
    let Some(dir) = nordland() else { return };
    let summer = nordland_files(&dir.join("summer"));
    let winter = nordland_files(&dir.join("winter"));
    let read = |files: &[std::path::PathBuf]| -> Vec<(String, Vec<u8>)> {
        files
            .iter()
            .map(|p| {
                (
                    p.file_name().unwrap().to_string_lossy().into_owned(),
                    std::fs::read(p).unwrap(),
                )
            })
            .collect()
    };
    // References 100..400 in two batches; queries: winter frames 200..300 (truth = index + 100).
    let refs = read(&summer[100..400]);
    let queries = read(&winter[200..300]);
    let server = Server::start();
    let c = server.client;
    let map = create_hog_map(&c, "nordland", 8);
    upload(&c, &map, &refs[..150], None);
    upload(&c, &map, &refs[150..], None);
    let result = run_localize(
        &c,
        &map,
        &queries,
        &json!({"fan_out": 4, "hidden_cost": 1.3}),
    );
    let preds = result["predictions"].as_array().unwrap();
    let correct = preds
        .iter()
        .filter(|p| (p["ref"].as_i64().unwrap() - (p["query"].as_i64().unwrap() + 100)).abs() <= 1)
        .count();
    eprintln!(
        "nordland over HTTP: {correct} of {} queries within ±1 frame",
        queries.len()
    );
    assert!(
        correct * 3 >= queries.len(),
        "only {correct} of {} correct",
        queries.len()
    );
    let options = LocalizeOptions {
        solver: SolverParams {
            hidden_cost: HiddenCost::Fixed(1.3),
            ..SolverParams::default()
        },
        normalization: seasonloc_core::similarity::Normalization::default(),
        ..Default::default()
    };
    let rb: Vec<Vec<u8>> = refs.iter().map(|(_, b)| b.clone()).collect();
    let qb: Vec<Vec<u8>> = queries.iter().map(|(_, b)| b.clone()).collect();
    assert_same_as_library(&result, &library(&rb, &qb, 8, &options));
}
