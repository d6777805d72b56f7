//! CNN maps over HTTP: creation records the model's identity, append, localize and trips equal
//! the library on the same images, every creation error is a precise 400, and a model file
//! changed after creation is 409 `model_mismatch` that stores nothing. Needs the shipped model
//! (`../shared/models`); each test prints a message and passes when it is absent.

use std::path::{Path, PathBuf};

use serde_json::{json, Value};

use seasonloc_core::features::cnn::{CnnOptions, CnnResize, CnnSpec};
use seasonloc_core::localize::{localize, LocalizeOptions};

use crate::common::{library_descriptors, Route, Server};
use crate::http::{Client, Part};
use crate::spec::check;

const MODEL: &str = "models/efficientnet-lite0-224.onnx";

/// The shipped model where the tests find it (`seasonloc_test_support::datasets`), if present.
fn shipped_model() -> Option<PathBuf> {
    seasonloc_test_support::datasets::resolve(MODEL)
}

/// A private copy of the model in a temporary folder (the tests overwrite it).
fn model_copy() -> Option<(tempfile::TempDir, PathBuf)> {
    let model = shipped_model()?;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.onnx");
    std::fs::copy(&model, &path).unwrap();
    Some((dir, path))
}

/// A server whose `--model-dir` holds a private copy of the model, and that copy's path; the
/// folder lives as long as the returned guard.
fn server_with_model_copy() -> Option<(tempfile::TempDir, PathBuf, Server)> {
    let (dir, model) = model_copy()?;
    let models = dir.path().to_path_buf();
    let server = Server::start_with(move |a| a.model_dir = Some(models));
    Some((dir, model, server))
}

fn create(c: &Client, descriptor: Value) -> crate::http::Response {
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": "cnn", "descriptor": descriptor}),
    );
    check("post", "/v1/maps", &r);
    r
}

fn images(
    c: &Client,
    path: &str,
    pngs: &[Vec<u8>],
    params: Option<Value>,
) -> crate::http::Response {
    let mut parts: Vec<Part> = pngs
        .iter()
        .enumerate()
        .map(|(i, b)| Part::image(&format!("f{i}.png"), b.clone()))
        .collect();
    if let Some(p) = params {
        parts.push(Part::json("params", &p));
    }
    c.post_multipart(path, &parts)
}

/// The descriptor both flow tests use: `block10` of the model, whole frame stretched.
fn stretch_block10(model: &Path) -> Value {
    json!({"kind": "cnn", "model": model, "layer": "block10", "resize": "stretch"})
}

/// References 0..16 of a generated route and queries of its places 4..12.
fn route_pngs() -> (Vec<Vec<u8>>, Vec<Vec<u8>>) {
    let route = Route::new(16, 3);
    let refs = (0..16).map(|i| route.reference_png(i)).collect();
    let queries = (4..12).map(|i| route.query_png(i)).collect();
    (refs, queries)
}

#[test]
fn cnn_map_equals_the_library_and_records_the_model_identity() {
    let Some((_dir, model, server)) = server_with_model_copy() else {
        return;
    };
    let c = &server.client;
    let r = create(c, stretch_block10(&model));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let map = r.json();
    let id = map["id"].as_str().unwrap().to_string();
    let d = &map["descriptor"];
    assert_eq!(d["kind"], "cnn");
    assert_eq!(d["layer"], "block10");
    assert_eq!(d["input_size"], json!([224, 224]));
    assert_eq!(d["resize"], "stretch");
    assert_eq!(d["mean"], json!([127.0, 127.0, 127.0]));
    let options = CnnOptions {
        resize: CnnResize::Stretch,
        ..CnnOptions::efficientnet_lite0(&model)
    };
    let spec = CnnSpec::new(options).unwrap();
    let identity = spec.identity();
    assert_eq!(d["identity"]["sha256"], identity.sha256.as_str());
    assert_eq!(d["identity"]["layer"], "block10");
    assert_eq!(
        d["identity"]["preprocessing"],
        identity.preprocessing.as_str()
    );

    let (refs, queries) = route_pngs();
    for (a, b) in [(0, 10), (10, 16)] {
        let r = images(c, &format!("/v1/maps/{id}/images"), &refs[a..b], None);
        check("post", "/v1/maps/{id}/images", &r);
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    }
    let got = c.get(&format!("/v1/maps/{id}")).json();
    assert_eq!(got["image_count"], 16);
    assert_eq!(got["descriptor_dim"], 21952);
    assert_eq!(got["descriptor"], map["descriptor"]);

    let params =
        json!({"fan_out": 4, "hidden_cost": 1.5, "flows": 1, "exact": false, "horizontal": true});
    let r = images(
        c,
        &format!("/v1/maps/{id}/localize"),
        &queries,
        Some(params),
    );
    check("post", "/v1/maps/{id}/localize", &r);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let http = r.json();

    let options = LocalizeOptions {
        solver: seasonloc_core::solver::SolverParams {
            fan_out: 4,
            hidden_cost: seasonloc_core::solver::HiddenCost::Fixed(1.5),
            flows: 1,
            exact: false,
            horizontal: true,
            stop_hidden_fraction: None,
        },
        normalization: seasonloc_core::similarity::Normalization::default(),
        ..Default::default()
    };
    let lib = localize(
        &library_descriptors(&spec, &queries),
        &library_descriptors(&spec, &refs),
        &options,
    )
    .unwrap();
    let preds = http["predictions"].as_array().unwrap();
    assert_eq!(preds.len(), lib.predictions.len());
    for (h, l) in preds.iter().zip(&lib.predictions) {
        assert_eq!(h["query"].as_u64().unwrap() as usize, l.query);
        assert_eq!(h["ref"].as_u64().unwrap() as usize, l.reference);
        assert_eq!(h["confidence"].as_f64().unwrap(), l.confidence);
    }
    assert_eq!(
        http["total_cost"].as_f64().unwrap(),
        lib.solution.total_cost()
    );
}

#[test]
fn cnn_map_creation_errors_are_precise_400s_and_422s() {
    let Some((dir, model, server)) = server_with_model_copy() else {
        return;
    };
    let c = &server.client;
    // 400 `invalid_parameter` for a value the OpenAPI document rules out; 422
    // `inconsistent_parameter` for one it allows that the model, another field or the server's
    // configuration refuses.
    let check = |descriptor: Value, status: u16, code: &str, field: &str, needle: &str| {
        let r = create(c, descriptor.clone());
        assert_eq!(
            r.status,
            status,
            "{descriptor}: {}",
            String::from_utf8_lossy(&r.body)
        );
        assert_eq!(r.code(), code, "{descriptor}");
        let m = r.message();
        assert!(m.contains(field), "{descriptor}: `{field}` not in {m}");
        assert!(m.contains(needle), "{descriptor}: `{needle}` not in {m}");
    };
    let expect =
        |d: Value, field: &str, needle: &str| check(d, 400, "invalid_parameter", field, needle);
    let refused = |d: Value, field: &str, needle: &str| {
        check(d, 422, "inconsistent_parameter", field, needle)
    };
    let missing = dir.path().join("absent.onnx");
    refused(
        json!({"kind": "cnn", "model": missing, "layer": "block10"}),
        "descriptor.model",
        "absent.onnx",
    );
    let garbage = dir.path().join("garbage.onnx");
    std::fs::write(&garbage, b"this is not a protobuf").unwrap();
    refused(
        json!({"kind": "cnn", "model": garbage, "layer": "block10"}),
        "descriptor.model",
        "garbage.onnx",
    );
    // The unknown layer's message lists the model's outputs.
    refused(
        json!({"kind": "cnn", "model": model, "layer": "block99"}),
        "descriptor.layer",
        "pooled",
    );
    // Too small for the network's strides.
    refused(
        json!({"kind": "cnn", "model": model, "layer": "block10", "input_size": [8, 8],
               "resize": "stretch"}),
        "descriptor.input_size",
        "8x8",
    );
    expect(
        json!({"kind": "cnn", "model": model, "layer": "block10", "input_size": [0, 224]}),
        "descriptor.input_size",
        "0x224",
    );
    expect(
        json!({"kind": "cnn", "model": model, "layer": "block10", "scale": [1, 0, 1]}),
        "descriptor.scale",
        "non-zero",
    );
    // Non-zero in JSON but 0 as an f32.
    expect(
        json!({"kind": "cnn", "model": model, "layer": "block10", "scale": [1, 1, -1e-46]}),
        "descriptor.scale",
        "non-zero",
    );
    refused(
        json!({"kind": "cnn", "model": model, "layer": "block10", "resize": "stretch", "short_side": 300}),
        "descriptor.short_side",
        "crop",
    );
    // No model and no server default.
    refused(
        json!({"kind": "cnn", "layer": "block10"}),
        "descriptor.model",
        "--cnn-model",
    );
    // The identity is the server's to record.
    expect(
        json!({"kind": "cnn", "model": model, "layer": "block10",
               "identity": {"sha256": "00", "layer": "block10", "preprocessing": "x"}}),
        "descriptor.identity",
        "server",
    );
    let maps = c.get("/v1/maps").json();
    assert_eq!(maps["maps"], json!([]), "no failed creation left a map");
}

#[test]
fn the_servers_default_model_is_used_when_the_body_names_none() {
    let Some((_dir, model)) = model_copy() else {
        return;
    };
    let m = model.clone();
    let server = Server::start_with(move |a| a.cnn_model = Some(m));
    let r = create(&server.client, json!({"kind": "cnn", "layer": "pooled"}));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let d = &r.json()["descriptor"];
    assert_eq!(d["model"], model.to_str().unwrap());
    assert_eq!(d["resize"], "crop");
    assert_eq!(d["short_side"], 256);
}

#[test]
fn a_model_file_changed_after_creation_is_a_409_that_stores_nothing() {
    let Some((_dir, model, server)) = server_with_model_copy() else {
        return;
    };
    let c = &server.client;
    let r = create(c, json!({"kind": "cnn", "model": model, "layer": "pooled"}));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let id = r.json()["id"].as_str().unwrap().to_string();
    let route = Route::new(6, 5);
    let refs: Vec<Vec<u8>> = (0..6).map(|i| route.reference_png(i)).collect();
    let r = images(c, &format!("/v1/maps/{id}/images"), &refs[..3], None);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));

    let original = std::fs::read(&model).unwrap();
    // Truncated: no longer loads.
    std::fs::write(&model, &original[..original.len() / 2]).unwrap();
    let r = images(c, &format!("/v1/maps/{id}/images"), &refs[3..], None);
    check("post", "/v1/maps/{id}/images", &r);
    assert_eq!(r.status, 409, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.code(), "model_mismatch");
    assert!(r.message().contains("no longer loads"), "{}", r.message());
    let r = images(c, &format!("/v1/maps/{id}/localize"), &refs[..2], None);
    check("post", "/v1/maps/{id}/localize", &r);
    assert_eq!(r.status, 409);
    assert_eq!(r.code(), "model_mismatch");
    // Gone.
    std::fs::remove_file(&model).unwrap();
    let r = images(c, &format!("/v1/maps/{id}/localize"), &refs[..2], None);
    assert_eq!(r.status, 409);
    assert_eq!(r.code(), "model_mismatch");
    assert_eq!(c.get(&format!("/v1/maps/{id}")).json()["image_count"], 3);

    // Restored byte for byte: the map works again (identity is the content, not the path).
    std::fs::write(&model, &original).unwrap();
    let r = images(c, &format!("/v1/maps/{id}/images"), &refs[3..], None);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let r = images(c, &format!("/v1/maps/{id}/localize"), &refs[..4], None);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(c.get(&format!("/v1/maps/{id}")).json()["image_count"], 6);

    // Another valid ONNX file at the path (here: same graph, one weight byte changed) is a
    // different model: 409 naming the hash.
    let mut other = original.clone();
    let k = other.len() / 2;
    other[k] ^= 0x01;
    std::fs::write(&model, &other).unwrap();
    let r = images(c, &format!("/v1/maps/{id}/localize"), &refs[..2], None);
    assert_eq!(r.status, 409, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.code(), "model_mismatch");
    assert!(r.message().contains("sha256"), "{}", r.message());
}

/// Trips on a CNN map describe their frames with the map's model: the latest estimate equals
/// `/localize` of the same frames (F = 1, raw similarities, fixed `W`, no relocalization), and
/// a model changed after creation is 409 `model_mismatch` that leaves the trip as it was.
#[test]
fn trips_on_a_cnn_map_use_its_model_and_refuse_a_changed_one() {
    let Some((_dir, model, server)) = server_with_model_copy() else {
        return;
    };
    let c = &server.client;
    let r = create(c, stretch_block10(&model));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let id = r.json()["id"].as_str().unwrap().to_string();
    let (refs, queries) = route_pngs();
    let r = images(c, &format!("/v1/maps/{id}/images"), &refs, None);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));

    let r = c.post_json(
        &format!("/v1/maps/{id}/trips"),
        &json!({"fan_out": 4, "hidden_cost": 1.5, "horizontal": true,
                "relocalization": false, "normalize": false}),
    );
    check("post", "/v1/maps/{id}/trips", &r);
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let trip = r.json()["id"].as_str().unwrap().to_string();
    let frames = format!("/v1/trips/{trip}/frames");
    let params = json!({"fan_out": 4, "hidden_cost": 1.5, "flows": 1, "exact": false,
                        "horizontal": true, "normalize": false});
    for (a, b) in [(0, 5), (5, 8)] {
        let r = images(c, &frames, &queries[a..b], None);
        check("post", "/v1/trips/{id}/frames", &r);
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        let got = r.json();
        let estimates = got["estimates"].as_array().unwrap();
        assert_eq!(estimates.len(), b - a);
        let latest = estimates.last().unwrap();
        assert_eq!(latest["frame"].as_u64().unwrap() as usize, b - 1);
        // Offline over the frames so far: the latest frame's prediction (absent = hidden).
        let r = images(
            c,
            &format!("/v1/maps/{id}/localize"),
            &queries[..b],
            Some(params.clone()),
        );
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        let offline = r.json()["predictions"]
            .as_array()
            .unwrap()
            .iter()
            .find(|p| p["query"].as_u64() == Some(b as u64 - 1))
            .map(|p| p["ref"].clone())
            .unwrap_or(Value::Null);
        assert_eq!(latest["ref"], offline, "frame {}", b - 1);
    }

    // The model file changes: frames are refused, the trip keeps its 8 frames.
    let original = std::fs::read(&model).unwrap();
    std::fs::write(&model, &original[..original.len() / 2]).unwrap();
    let r = images(c, &frames, &queries[..2], None);
    check("post", "/v1/trips/{id}/frames", &r);
    assert_eq!(r.status, 409, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.code(), "model_mismatch");
    assert_eq!(c.get(&format!("/v1/trips/{trip}")).json()["frame_count"], 8);
}

/// The model file is read under the model directory's rules at every use (issue 42, defect 6):
/// replaced by a FIFO while three appends wait on two CPU-pool threads, every append is a 409
/// `model_mismatch` at once and another map's localize answers; replaced by a link to
/// `/dev/zero`, an append is a 409 too. Before, the FIFO held both pool threads (the HOG
/// localize below timed out) and `/dev/zero` was read until memory ran out.
#[cfg(unix)]
#[test]
fn a_model_replaced_by_a_fifo_or_a_device_is_refused_without_holding_the_pool() {
    use std::sync::mpsc;
    use std::time::Duration;
    let Some((_dir, model, server)) = server_with_model_copy() else {
        return;
    };
    let c = &server.client;
    let r = create(c, json!({"kind": "cnn", "model": model, "layer": "pooled"}));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let cnn = r.json()["id"].as_str().unwrap().to_string();
    let route = Route::new(8, 9);
    let refs: Vec<Vec<u8>> = (0..8u32).map(|i| route.reference_png(i)).collect();
    let r = images(c, &format!("/v1/maps/{cnn}/images"), &refs[..3], None);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let hog = crate::common::create_hog_map(c, "hog", 8);
    let r = images(c, &format!("/v1/maps/{hog}/images"), &refs, None);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));

    std::fs::remove_file(&model).unwrap();
    let made = std::process::Command::new("mkfifo").arg(&model).status();
    if !made.is_ok_and(|s| s.success()) {
        eprintln!("skipped: mkfifo is not available");
        return;
    }
    let (tx, rx) = mpsc::channel();
    for _ in 0..3 {
        let (client, tx, path) = (*c, tx.clone(), format!("/v1/maps/{cnn}/images"));
        let part = refs[3].clone();
        std::thread::spawn(move || {
            let parts = [Part::image("f.png", part)];
            let _ = tx.send(client.post_multipart(&path, &parts));
        });
    }
    let localize = {
        let (client, path) = (*c, format!("/v1/maps/{hog}/localize"));
        let queries = refs[2..6].to_vec();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(500));
            let _ = tx.send(images(&client, &path, &queries, None));
        });
        rx.recv_timeout(Duration::from_secs(30))
    };
    let appends: Vec<_> = (0..3)
        .map(|_| rx.recv_timeout(Duration::from_secs(30)))
        .collect();
    // Before the fix the appends block in open(2) until a writer comes: release them.
    let fifo = model.clone();
    std::thread::spawn(move || {
        for _ in 0..3 {
            let _ = std::fs::OpenOptions::new().write(true).open(&fifo);
        }
    });
    let localize = localize.expect("a HOG localize on another map did not answer within 30 s");
    assert_eq!(localize.status, 200, "{}", localize.message());
    for a in appends {
        let a = a.expect("a CNN append with the model replaced by a FIFO hung");
        assert_eq!(a.status, 409, "{}", String::from_utf8_lossy(&a.body));
        assert_eq!(a.code(), "model_mismatch");
    }

    std::fs::remove_file(&model).unwrap();
    std::os::unix::fs::symlink("/dev/zero", &model).unwrap();
    let r = images(c, &format!("/v1/maps/{cnn}/images"), &refs[3..4], None);
    assert_eq!(r.status, 409, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.code(), "model_mismatch");
    assert!(
        r.message().contains("may no longer be read"),
        "{}",
        r.message()
    );
    assert_eq!(c.get(&format!("/v1/maps/{cnn}")).json()["image_count"], 3);
}
