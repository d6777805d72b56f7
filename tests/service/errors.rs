//! Every bad input gets a precise 4xx with the documented error shape, and a failed upload
//! writes nothing.

use serde_json::json;

use crate::common::{create_hog_map, create_vector_map, png, Route, Server};
use crate::http::{Client, Part};
use crate::spec::check;

const MAX_BODY: usize = 200_000;

fn strict_server() -> Server {
    Server::start_with(|a| {
        a.max_batch_images = 4;
        a.max_image_pixels = 64 * 32;
        a.max_body_bytes = MAX_BODY;
    })
}

fn image_count(c: &Client, map: &str) -> u64 {
    c.get(&format!("/v1/maps/{map}")).json()["image_count"]
        .as_u64()
        .unwrap()
}

fn expect(r: &crate::http::Response, method: &str, template: &str, status: u16, code: &str) {
    check(method, template, r);
    assert_eq!(
        (r.status, r.code().as_str()),
        (status, code),
        "{method} {template}: {}",
        String::from_utf8_lossy(&r.body)
    );
}

#[test]
fn unknown_ids_are_404() {
    let server = strict_server();
    let c = server.client;
    for id in ["ffffffffffffffff", "not-an-id"] {
        expect(
            &c.get(&format!("/v1/maps/{id}")),
            "get",
            "/v1/maps/{id}",
            404,
            "map_not_found",
        );
        expect(
            &c.delete(&format!("/v1/maps/{id}")),
            "delete",
            "/v1/maps/{id}",
            404,
            "map_not_found",
        );
        let r = c.post_multipart(
            &format!("/v1/maps/{id}/images"),
            &[Part::image("a.png", vec![1])],
        );
        expect(&r, "post", "/v1/maps/{id}/images", 404, "map_not_found");
        let r = c.post_json(
            &format!("/v1/maps/{id}/localize"),
            &json!({"descriptors": [[1.0]]}),
        );
        expect(&r, "post", "/v1/maps/{id}/localize", 404, "map_not_found");
        let r = c.get(&format!("/v1/localizations/{id}"));
        expect(
            &r,
            "get",
            "/v1/localizations/{id}",
            404,
            "localization_not_found",
        );
        let r = c.get(&format!("/v1/localizations?map={id}"));
        expect(&r, "get", "/v1/localizations", 404, "map_not_found");
    }
    assert!(c
        .get("/v1/maps/ffffffffffffffff")
        .message()
        .contains("ffffffffffffffff"));
}

#[test]
fn bad_map_settings_are_400_or_422() {
    let server = strict_server();
    let c = server.client;
    let cases = [
        (json!({"name": "", "descriptor": {"kind": "hog"}}), "name"),
        (
            json!({"name": "a", "descriptor": {"kind": "hog", "cell_size": 0}}),
            "cell_size",
        ),
        (
            json!({"name": "a", "descriptor": {"kind": "hog", "cel_size": 8}}),
            "cel_size",
        ),
        (json!({"name": "a", "descriptor": {"kind": "sift"}}), "sift"),
        (
            json!({"name": "a", "descriptor": {"kind": "precomputed", "dim": 0}}),
            "dim",
        ),
        (json!({"name": "a", "colour": "red"}), "colour"),
    ];
    for (body, needle) in cases {
        let r = c.post_json("/v1/maps", &body);
        expect(&r, "post", "/v1/maps", 400, "invalid_parameter");
        assert!(r.message().contains(needle), "{body}: {}", r.message());
    }
    // Lengths are characters, as the document's `maxLength` counts them.
    let long = "é".repeat(200);
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": long, "descriptor": {"kind": "hog"}}),
    );
    check("post", "/v1/maps", &r);
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    c.request(
        "DELETE",
        &format!("/v1/maps/{}", r.json()["id"].as_str().unwrap()),
        None,
        b"",
    );
    // A NUL is refused on every engine (PostgreSQL's text cannot hold it: it was a 500 there).
    for name in [
        "é".repeat(201),
        "   ".to_string(),
        "route\u{0}7".to_string(),
    ] {
        let r = c.post_json(
            "/v1/maps",
            &json!({"name": name, "descriptor": {"kind": "hog"}}),
        );
        expect(&r, "post", "/v1/maps", 400, "invalid_parameter");
        assert!(r.message().contains("`name`"), "{name:?}: {}", r.message());
    }
    // Valid by the schema, refused by what the server has: no model directory here, and a
    // spatial tolerance that does not fit its grid.
    let inconsistent = [
        (
            json!({"name": "a", "descriptor": {"kind": "cnn", "model": "m.onnx", "layer": "x"}}),
            "descriptor.model",
        ),
        (
            json!({"name": "a", "descriptor": {"kind": "cooc", "grid": [2, 2], "spatial_tolerance": 2}}),
            "descriptor.spatial_tolerance",
        ),
    ];
    for (body, needle) in inconsistent {
        let r = c.post_json("/v1/maps", &body);
        expect(&r, "post", "/v1/maps", 422, "inconsistent_parameter");
        assert!(r.message().contains(needle), "{body}: {}", r.message());
    }
    let r = c.request("POST", "/v1/maps", Some("application/json"), b"{\"name\": ");
    expect(&r, "post", "/v1/maps", 400, "bad_request");
    let r = c.request("POST", "/v1/maps", Some("text/plain"), b"{}");
    expect(&r, "post", "/v1/maps", 415, "unsupported_media_type");
    assert!(c.get("/v1/maps").json()["maps"]
        .as_array()
        .unwrap()
        .is_empty());
}

#[test]
fn bad_image_batches_are_rejected_whole() {
    let server = strict_server();
    let c = server.client;
    let route = Route::new(8, 3);
    let map = create_hog_map(&c, "strict", 8);
    let path = format!("/v1/maps/{map}/images");
    let t = "/v1/maps/{id}/images";
    let good = |i| Part::image(&format!("f{i}.png"), route.reference_png(i));
    let r = c.post_multipart(&path, &[good(0)]);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));

    // Corrupt (not an image) and truncated PNG, each naming its part.
    let r = c.post_multipart(
        &path,
        &[
            good(1),
            Part::image("bad.png", b"definitely not a png".to_vec()),
        ],
    );
    expect(&r, "post", t, 422, "invalid_image");
    assert!(
        r.message().contains("image[1]") && r.message().contains("bad.png"),
        "{}",
        r.message()
    );
    let mut truncated = route.reference_png(2);
    truncated.truncate(truncated.len() / 2);
    let r = c.post_multipart(&path, &[Part::image("cut.png", truncated), good(3)]);
    expect(&r, "post", t, 422, "invalid_image");
    assert!(r.message().contains("cut.png"), "{}", r.message());

    // Over the pixel limit.
    let big = png(&image::GrayImage::new(65, 32));
    let r = c.post_multipart(&path, &[good(1), Part::image("big.png", big)]);
    expect(&r, "post", t, 413, "image_too_large");
    assert!(
        r.message().contains("big.png") && r.message().contains("65x32"),
        "{}",
        r.message()
    );

    // Smaller than one HOG cell: too small to bring to the map's input geometry (another
    // size is fine, see flow::images_of_any_size_are_brought_to_the_map_geometry).
    let small = png(&image::GrayImage::new(4, 32));
    let r = c.post_multipart(&path, &[Part::image("small.png", small)]);
    expect(&r, "post", t, 422, "invalid_image");
    assert!(r.message().contains("small.png"), "{}", r.message());

    // Empty batch, batch over the count limit, unknown part, bad metadata.
    let r = c.post_multipart(&path, &[]);
    expect(&r, "post", t, 400, "empty_batch");
    let r = c.post_multipart(&path, &[Part::json("metadata", &json!([]))]);
    expect(&r, "post", t, 400, "empty_batch");
    let five: Vec<Part> = (0..5).map(good).collect();
    let r = c.post_multipart(&path, &five);
    expect(&r, "post", t, 400, "batch_too_large");
    let r = c.post_multipart(&path, &[good(1), Part::json("photo", &json!(1))]);
    expect(&r, "post", t, 400, "bad_request");
    assert!(r.message().contains("photo"));
    let r = c.post_multipart(
        &path,
        &[
            good(1),
            Part::json("metadata", &json!([{"latitude": 123.0}])),
        ],
    );
    expect(&r, "post", t, 400, "invalid_parameter");
    assert!(
        r.message().contains("metadata[0].latitude"),
        "{}",
        r.message()
    );
    let r = c.post_multipart(
        &path,
        &[good(1), good(2), Part::json("metadata", &json!([{}]))],
    );
    // Valid by the schema, but one entry for two images: 422, never 400.
    expect(&r, "post", t, 422, "inconsistent_parameter");
    assert!(r.message().contains("metadata"), "{}", r.message());

    // Over the body limit.
    let huge = vec![7u8; MAX_BODY + 1];
    let r = c.post_multipart(&path, &[Part::image("huge.png", huge)]);
    expect(&r, "post", t, 413, "payload_too_large");

    // Not multipart at all.
    let r = c.post_json(&path, &json!({}));
    expect(&r, "post", t, 415, "unsupported_media_type");

    assert_eq!(image_count(&c, &map), 1, "a failed batch wrote something");
}

#[test]
fn bad_descriptors_are_rejected_whole() {
    let server = strict_server();
    let c = server.client;
    let map = create_vector_map(&c, "vectors", 3);
    let path = format!("/v1/maps/{map}/descriptors");
    let t = "/v1/maps/{id}/descriptors";
    let r = c.post_json(&path, &json!({"descriptors": [[1, 2, 3], [1, 2]]}));
    expect(&r, "post", t, 422, "descriptor_length");
    assert!(r.message().contains("descriptors[1]"), "{}", r.message());
    let r = c.post_json(&path, &json!({"descriptors": [[1, 2, 1e39]]}));
    expect(&r, "post", t, 422, "non_finite");
    let nan: Vec<u8> = [1.0f32, f32::NAN, 3.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let r = c.request("POST", &path, Some("application/octet-stream"), &nan);
    expect(&r, "post", t, 422, "non_finite");
    assert!(r.message().contains("descriptors[0][1]"), "{}", r.message());
    let r = c.request("POST", &path, Some("application/octet-stream"), &nan[..8]);
    expect(&r, "post", t, 422, "descriptor_length");
    let r = c.post_json(&path, &json!({"descriptors": []}));
    expect(&r, "post", t, 400, "empty_batch");
    let r = c.post_json(&path, &json!({"descriptors": vec![vec![1, 2, 3]; 5]}));
    expect(&r, "post", t, 400, "batch_too_large");
    let r = c.post_json(&path, &json!({"descriptors": [["a", 2, 3]]}));
    expect(&r, "post", t, 400, "invalid_parameter");
    let r = c.request("POST", &path, Some("text/csv"), b"1,2,3");
    expect(&r, "post", t, 415, "unsupported_media_type");
    let long = format!(
        "{{\"descriptors\": [[{}]]}}",
        vec!["1.0"; MAX_BODY / 3].join(",")
    );
    let r = c.request("POST", &path, Some("application/json"), long.as_bytes());
    expect(&r, "post", t, 413, "payload_too_large");
    assert_eq!(image_count(&c, &map), 0, "a failed batch wrote something");
    // Images to a precomputed map: a request this kind of map does not take.
    let r = c.post_multipart(
        &format!("/v1/maps/{map}/images"),
        &[Part::image("a.png", vec![1, 2])],
    );
    expect(&r, "post", "/v1/maps/{id}/images", 409, "map_kind");
}

#[test]
fn bad_localize_requests_are_rejected() {
    let server = strict_server();
    let c = server.client;
    let map = create_vector_map(&c, "vectors", 2);
    let path = format!("/v1/maps/{map}/localize");
    let t = "/v1/maps/{id}/localize";
    let r = c.post_json(&path, &json!({"descriptors": [[1, 0]]}));
    expect(&r, "post", t, 409, "map_empty");
    let r = c.post_json(
        &format!("/v1/maps/{map}/descriptors"),
        &json!({"descriptors": [[1, 0], [0, 1], [1, 1]]}),
    );
    assert_eq!(r.status, 200);
    let cases = [
        (json!({"fanout": 3}), "fanout"),
        (json!({"fan_out": 5000}), "fan_out"),
        (json!({"flows": 0}), "flows"),
        (json!({"flows": 65}), "flows"),
        (json!({"hidden_cost": -1.0}), "hidden_cost"),
        (json!({"hidden_cost": "high"}), "hidden_cost"),
        (json!({"stop_hidden_fraction": 2.0}), "stop_hidden_fraction"),
        (json!({"exact": "yes"}), "exact"),
    ];
    for (params, needle) in cases {
        let r = c.post_json(&path, &json!({"descriptors": [[1, 0]], "params": params}));
        expect(&r, "post", t, 400, "invalid_parameter");
        assert!(r.message().contains(needle), "{params}: {}", r.message());
        // The same through the multipart `params` part.
        let r = c.post_multipart(
            &path,
            &[Part::image("q.png", vec![1]), Part::json("params", &params)],
        );
        expect(&r, "post", t, 400, "invalid_parameter");
    }
    let r = c.post_json(&path, &json!({"descriptors": [[1, 0, 0]]}));
    expect(&r, "post", t, 422, "descriptor_length");
    let r = c.post_json(&path, &json!({"descriptors": []}));
    expect(&r, "post", t, 400, "empty_batch");
    let r = c.post_multipart(&path, &[]);
    expect(&r, "post", t, 400, "empty_batch");
    let r = c.request("POST", &path, Some("text/plain"), b"hello");
    expect(&r, "post", t, 415, "unsupported_media_type");
    let r = c.get("/v1/localizations?limit=0");
    expect(&r, "get", "/v1/localizations", 400, "invalid_parameter");
    let r = c.get("/v1/localizations?colour=red");
    expect(&r, "get", "/v1/localizations", 400, "invalid_parameter");
    let r = c.get("/v1/localizations?before=xyz");
    expect(&r, "get", "/v1/localizations", 400, "invalid_parameter");
    let r = c.get("/v1/localizations");
    assert_eq!(
        r.json()["items"].as_array().unwrap().len(),
        0,
        "a failed localization was stored"
    );
}

#[test]
fn full_localize_queue_answers_503_with_retry_after() {
    let server = Server::start_with(|a| a.localize_queue = 1);
    let c = server.client;
    let map = create_vector_map(&c, "queue", 16);
    let refs: Vec<Vec<f32>> = (0..1500)
        .map(|i| {
            (0..16)
                .map(|k| ((i * 7 + k * 13) % 17) as f32 + 1.0)
                .collect()
        })
        .collect();
    let r = c.post_json(
        &format!("/v1/maps/{map}/descriptors"),
        &json!({"descriptors": refs}),
    );
    assert_eq!(r.status, 200);
    let body = serde_json::to_vec(&json!({"descriptors": &refs[..400]})).unwrap();
    let path = format!("/v1/maps/{map}/localize");
    for _attempt in 0..20 {
        let results: Vec<crate::http::Response> = std::thread::scope(|s| {
            let handles: Vec<_> = (0..8)
                .map(|_| s.spawn(|| c.request("POST", &path, Some("application/json"), &body)))
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        for r in &results {
            assert!(
                r.status == 200 || r.status == 503,
                "{}",
                String::from_utf8_lossy(&r.body)
            );
            check("post", "/v1/maps/{id}/localize", r);
        }
        if let Some(busy) = results.iter().find(|r| r.status == 503) {
            assert_eq!(busy.code(), "queue_full");
            assert_eq!(busy.header("retry-after"), Some("1"));
            let metrics = String::from_utf8(c.get("/metrics").body).unwrap();
            assert!(
                !metrics.contains("seasonloc_localize_rejected_total 0"),
                "{metrics}"
            );
            return;
        }
    }
    panic!("8 concurrent localizations never filled a queue of 1");
}

#[test]
fn responses_carry_a_request_id() {
    let server = Server::start();
    let r = server.client.get("/healthz");
    check("get", "/healthz", &r);
    assert_eq!(r.json()["status"], "ok");
    let id = r.header("x-request-id").expect("x-request-id header");
    assert!(id.len() >= 16, "{id}");
    let r = server.client.get("/readyz");
    check("get", "/readyz", &r);
}

/// The largest `f64` below a positive `x`.
fn f64_below(x: f64) -> f64 {
    f64::from_bits(x.to_bits() - 1)
}

/// The bounds the OpenAPI states are the server's: a value at a bound is served, one past it
/// is refused (schemathesis found the spec silent about them; see the README's test section).
#[test]
fn the_specs_numeric_bounds_are_the_servers() {
    let doc = crate::spec::doc();
    let f32_schema = &doc["components"]["schemas"]["Float32"];
    // The bounds are where rounding to f32 reaches infinity (2^128 - 2^103, a tie that rounds
    // to infinity: exclusive), not f32::MAX itself, whose JSON neighbours above still round to
    // f32::MAX and are accepted (schemathesis found -3.402823466385289e38 taken: ST201).
    let midpoint = 2f64.powi(128) - 2f64.powi(103);
    assert_eq!(midpoint as f32, f32::INFINITY);
    assert_eq!(f64_below(midpoint) as f32, f32::MAX);
    assert_eq!(f32_schema["maximum"].as_f64(), Some(midpoint));
    assert_eq!(f32_schema["minimum"].as_f64(), Some(-midpoint));
    assert_eq!(f32_schema["exclusiveMaximum"], true);
    assert_eq!(f32_schema["exclusiveMinimum"], true);
    let param_max = |path: &str, name: &str| -> Option<u64> {
        let op = &doc["paths"][path]["get"]["parameters"];
        let shared = &doc["paths"][path]["parameters"];
        op.as_array()
            .into_iter()
            .chain(shared.as_array())
            .flatten()
            .find(|p| p["name"] == name)
            .and_then(|p| p["schema"]["maximum"].as_u64())
    };
    let param_max_post = |path: &str, name: &str| -> Option<u64> {
        doc["paths"][path]["parameters"]
            .as_array()
            .into_iter()
            .flatten()
            .find(|p| p["name"] == name)
            .and_then(|p| p["schema"]["maximum"].as_u64())
    };
    let u32_max = u64::from(u32::MAX);
    assert_eq!(param_max("/v1/maps/{id}/images", "from"), Some(u32_max));
    assert_eq!(param_max("/v1/trips/{id}", "since"), Some(u32_max));
    assert_eq!(
        param_max("/v1/maps/{id}/images/{index}/thumbnail", "index"),
        Some(u32_max)
    );

    // Map settings: the spec's ranges are the library's.
    let schemas = &doc["components"]["schemas"];
    let range = |schema: &str, field: &str| {
        let f = &schemas[schema]["properties"][field];
        (f["minimum"].as_u64(), f["maximum"].as_u64())
    };
    use seasonloc::features::hog::{MAX_CELL_SIZE, MIN_CELL_SIZE};
    assert_eq!(
        range("HogDescriptor", "cell_size"),
        (Some(MIN_CELL_SIZE.into()), Some(MAX_CELL_SIZE.into()))
    );
    assert_eq!(range("CoocDescriptor", "upsample"), (Some(1), Some(8)));
    assert_eq!(
        range("CoocDescriptor", "max_keypoints"),
        (Some(1), Some(2000))
    );
    let grid = &schemas["CoocDescriptor"]["properties"]["grid"]["items"];
    assert_eq!(
        (grid["minimum"].as_u64(), grid["maximum"].as_u64()),
        (Some(1), Some(64))
    );

    use seasonloc::features::cnn::{MAX_INPUT_SIDE, MAX_SHORT_SIDE};
    let side = &schemas["CnnDescriptor"]["properties"]["input_size"]["items"];
    assert_eq!(
        (side["minimum"].as_u64(), side["maximum"].as_u64()),
        (Some(1), Some(MAX_INPUT_SIDE.into()))
    );
    assert_eq!(
        range("CnnDescriptor", "short_side"),
        (Some(1), Some(MAX_SHORT_SIDE.into()))
    );

    // A CNN divisor is a normal f32 (zero, subnormal or infinite ones make every pixel
    // infinite), so its bounds are the numbers that round to f32::MIN_POSITIVE..=f32::MAX on
    // either side of zero: from 2^-126 - 2^-150 (a tie that rounds to the even
    // f32::MIN_POSITIVE: inclusive) to below the midpoint; a mean is any Float32.
    let cnn = &schemas["CnnDescriptor"]["properties"];
    assert_eq!(cnn["mean"]["items"]["$ref"], "#/components/schemas/Float32");
    let tiny = 2f64.powi(-126) - 2f64.powi(-150);
    assert_eq!(tiny as f32, f32::MIN_POSITIVE);
    assert!(!(f64_below(tiny) as f32).is_normal());
    let huge = midpoint;
    let scale: Vec<_> = cnn["scale"]["items"]["oneOf"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            (
                r["minimum"].as_f64().unwrap(),
                r["maximum"].as_f64().unwrap(),
            )
        })
        .collect();
    assert_eq!(scale, [(tiny, huge), (-huge, -tiny)]);

    let server = strict_server();
    let c = server.client;
    // Divisors and means inside those bounds pass the settings' checks (the missing model
    // file is what is refused, 422); outside them a 400 names the field. The first 400 was
    // found by schemathesis: 1e-213, valid by the earlier document, is 0 as an f32.
    let (below_huge, below_tiny) = (f64_below(huge), f64_below(tiny));
    for (mean, scale, field) in [
        (
            json!([below_huge, -below_huge, 0]),
            json!([tiny, -tiny, below_huge]),
            None,
        ),
        (
            json!([1, 2, 3]),
            json!([below_tiny, 1, 1]),
            Some("descriptor.scale"),
        ),
        (
            json!([huge, 2, 3]),
            json!([1, 1, 1]),
            Some("descriptor.mean"),
        ),
        (
            json!([1, 2, 3]),
            json!([1, -huge, 1]),
            Some("descriptor.scale"),
        ),
        (
            json!([1, 2, 3]),
            json!([1e-213, 1, 1]),
            Some("descriptor.scale"),
        ),
        (
            json!([1, 2, 3]),
            json!([tiny / 2.0, 1, 1]),
            Some("descriptor.scale"),
        ),
        (json!([1, 2, 3]), json!([1, 1, 0]), Some("descriptor.scale")),
        (
            json!([1, 2, 3]),
            json!([1, 1e39, 1]),
            Some("descriptor.scale"),
        ),
        (
            json!([1, 1e39, 3]),
            json!([1, 1, 1]),
            Some("descriptor.mean"),
        ),
    ] {
        let descriptor = json!({"kind": "cnn", "model": "none.onnx", "layer": "x", "mean": mean, "scale": scale});
        let r = c.post_json("/v1/maps", &json!({"name": "b", "descriptor": descriptor}));
        let body = String::from_utf8_lossy(&r.body);
        match field {
            Some(field) => {
                expect(&r, "post", "/v1/maps", 400, "invalid_parameter");
                assert!(body.contains(field), "{descriptor}: {body}");
            }
            None => {
                expect(&r, "post", "/v1/maps", 422, "inconsistent_parameter");
                assert!(body.contains("descriptor.model"), "{descriptor}: {body}");
            }
        }
    }
    // CNN sides past the bounds are 400s naming them, checked before any model file is read
    // (an input side near u32::MAX once overflowed the default short side: a dropped
    // connection instead of an answer).
    for (descriptor, field) in [
        (
            json!({"kind": "cnn", "model": "none.onnx", "layer": "x", "input_size": [MAX_INPUT_SIDE + 1, 224]}),
            "descriptor.input_size",
        ),
        (
            json!({"kind": "cnn", "model": "none.onnx", "layer": "x", "input_size": [23745, 993679550]}),
            "descriptor.input_size",
        ),
        (
            json!({"kind": "cnn", "model": "none.onnx", "layer": "x", "input_size": [224, u32::MAX]}),
            "descriptor.input_size",
        ),
        (
            json!({"kind": "cnn", "model": "none.onnx", "layer": "x", "short_side": MAX_SHORT_SIDE + 1}),
            "descriptor.short_side",
        ),
    ] {
        let r = c.post_json("/v1/maps", &json!({"name": "b", "descriptor": descriptor}));
        expect(&r, "post", "/v1/maps", 400, "invalid_parameter");
        assert!(
            String::from_utf8_lossy(&r.body).contains(field),
            "{descriptor}: {}",
            String::from_utf8_lossy(&r.body)
        );
    }
    for (settings, ok) in [
        (json!({"kind": "hog", "cell_size": MIN_CELL_SIZE}), true),
        (json!({"kind": "hog", "cell_size": MAX_CELL_SIZE}), true),
        (
            json!({"kind": "hog", "cell_size": MIN_CELL_SIZE - 1}),
            false,
        ),
        (
            json!({"kind": "hog", "cell_size": MAX_CELL_SIZE + 1}),
            false,
        ),
        (
            json!({"kind": "cooc", "upsample": 8, "max_keypoints": 2000, "grid": [64, 1]}),
            true,
        ),
        (json!({"kind": "cooc", "grid": null}), true),
        (json!({"kind": "cooc", "upsample": 9}), false),
        (json!({"kind": "cooc", "max_keypoints": 2001}), false),
        (json!({"kind": "cooc", "grid": [65, 8]}), false),
    ] {
        let r = c.post_json("/v1/maps", &json!({"name": "b", "descriptor": settings}));
        check("post", "/v1/maps", &r);
        let want = if ok { 201 } else { 400 };
        assert_eq!(
            r.status,
            want,
            "{settings}: {}",
            String::from_utf8_lossy(&r.body)
        );
    }
    let map = create_vector_map(&c, "bounds", 3);
    let path = format!("/v1/maps/{map}/descriptors");
    let t = "/v1/maps/{id}/descriptors";
    let r = c.post_json(
        &path,
        &json!({"descriptors": [[f64::from(f32::MAX), f64::from(f32::MIN), 0.0]]}),
    );
    check("post", t, &r);
    assert!(r.status < 300, "{}", String::from_utf8_lossy(&r.body));
    let r = c.post_json(&path, &json!({"descriptors": [[1, 2, 3.5e38]]}));
    expect(&r, "post", t, 422, "non_finite");

    let images = "/v1/maps/{id}/images";
    let r = c.get(&format!("/v1/maps/{map}/images?from={}", u32::MAX));
    check("get", images, &r);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let r = c.get(&format!("/v1/maps/{map}/images?from={}", u32_max + 1));
    expect(&r, "get", images, 400, "invalid_parameter");
    let thumb = "/v1/maps/{id}/images/{index}/thumbnail";
    let r = c.get(&format!("/v1/maps/{map}/images/{}/thumbnail", u32::MAX));
    check("get", thumb, &r);
    assert_eq!(r.status, 404, "{}", String::from_utf8_lossy(&r.body));
    let r = c.get(&format!("/v1/maps/{map}/images/{}/thumbnail", u32_max + 1));
    expect(&r, "get", thumb, 400, "invalid_parameter");

    // A precomputed map's `dim` and the raw upload's `?dim=`: the document's bound is the
    // server's; within it, a length over this server's configured cap is a 422.
    let max_dim = 1u64 << 20; // the server's `MAX_DESCRIPTOR_DIM`, pinned over HTTP below
    assert_eq!(
        range("PrecomputedDescriptor", "dim"),
        (Some(1), Some(max_dim))
    );
    assert_eq!(
        param_max_post("/v1/maps/{id}/descriptors", "dim"),
        Some(max_dim)
    );
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": "d", "descriptor": {"kind": "precomputed", "dim": max_dim + 1}}),
    );
    expect(&r, "post", "/v1/maps", 400, "invalid_parameter");
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": "d", "descriptor": {"kind": "precomputed", "dim": max_dim}}),
    );
    check("post", "/v1/maps", &r);
    assert!(
        r.status == 201 || (r.status, r.code().as_str()) == (422, "inconsistent_parameter"),
        "{}",
        String::from_utf8_lossy(&r.body)
    );
    let r = c.request(
        "POST",
        &format!("{path}?dim={}", u64::from(u32::MAX) + 1),
        Some("application/octet-stream"),
        &[0; 12],
    );
    expect(&r, "post", t, 400, "invalid_parameter");
    let drive = &schemas["Drive"]["properties"]["locations"]["items"];
    assert_eq!(
        drive["maximum"].as_u64(),
        Some(seasonloc::cooc::model::MAX_LOCATIONS as u64 - 1)
    );

    // Dashboard pages: a well-formed id is the page (which asks the API whether it exists);
    // a path that cannot be an id is the API's 404.
    for (page, code) in [
        ("/maps/{id}", "map_not_found"),
        ("/localizations/{id}", "localization_not_found"),
        ("/trips/{id}", "trip_not_found"),
    ] {
        let r = c.get(&page.replace("{id}", "ffffffffffffffff"));
        check("get", page, &r);
        assert_eq!(r.status, 200, "{page}");
        let r = c.get(&page.replace("{id}", "not-an-id"));
        expect(&r, "get", page, 404, code);
    }
}

/// Every optional field of a request object is `nullable` in the document, because the server
/// reads `null` as "not given" (its default); the one exception is spelled out. And a body or
/// part that must be an object is refused when it is anything else, although serde would fill
/// a struct from an array.
#[test]
fn optional_fields_take_null_and_objects_must_be_objects() {
    let doc = crate::spec::doc();
    let schemas = &doc["components"]["schemas"];
    for (schema, required) in [
        ("HogDescriptor", &["kind", "cell_size"][..]),
        ("CnnDescriptor", &["kind", "layer"]),
        ("CoocDescriptor", &["kind"]),
        ("Drive", &["locations"]),
        ("ImageMetadata", &[]),
        ("AppendDescriptorsRequest", &["descriptors"]),
        ("LocalizeParams", &[]),
        ("TripParams", &[]),
    ] {
        let props = schemas[schema]["properties"].as_object().unwrap();
        for (name, p) in props {
            let nullable = p["nullable"] == json!(true);
            assert_eq!(
                nullable,
                !required.contains(&name.as_str()),
                "{schema}.{name}: nullable is {nullable}"
            );
            // An enum that omits null forbids it, whatever `nullable` says.
            if let (true, Some(values)) = (nullable, p["enum"].as_array()) {
                assert!(
                    values.contains(&json!(null)),
                    "{schema}.{name}: enum without null"
                );
            }
        }
    }

    let server = strict_server();
    let c = server.client;
    let route = Route::new(8, 3);
    let hog = create_hog_map(&c, "nulls", 8);
    let r = c.post_multipart(
        &format!("/v1/maps/{hog}/images"),
        &[Part::image("r.png", route.reference_png(0))],
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let trips = format!("/v1/maps/{hog}/trips");
    let r = c.post_json(
        &trips,
        &json!({"lag": null, "fan_out": null, "hidden_cost": null, "relocalization": null,
                "relocalization_cost": null, "prior_weight": null, "normalize": null,
                "horizontal": null}),
    );
    check("post", "/v1/maps/{id}/trips", &r);
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["params"]["lag"], 32, "null is the default");
    for body in ["[]", "[null, null]", "[4]"] {
        let r = c.request("POST", &trips, Some("application/json"), body.as_bytes());
        expect(&r, "post", "/v1/maps/{id}/trips", 400, "invalid_parameter");
        assert!(
            r.message().contains("JSON object"),
            "{body}: {}",
            r.message()
        );
    }
    let r = c.request(
        "POST",
        "/v1/maps",
        Some("application/json"),
        br#"["a", {"kind": "hog"}]"#,
    );
    expect(&r, "post", "/v1/maps", 400, "invalid_parameter");

    let vectors = create_vector_map(&c, "null-vectors", 2);
    let r = c.post_json(
        &format!("/v1/maps/{vectors}/descriptors"),
        &json!({"descriptors": [[1, 0]], "metadata": null}),
    );
    check("post", "/v1/maps/{id}/descriptors", &r);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let localize = format!("/v1/maps/{vectors}/localize");
    let r = c.post_json(
        &localize,
        &json!({"descriptors": [[1, 0]], "params": {"method": null, "flows": null}}),
    );
    check("post", "/v1/maps/{id}/localize", &r);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let r = c.request("POST", &localize, Some("application/json"), b"[[[1, 0]]]");
    expect(
        &r,
        "post",
        "/v1/maps/{id}/localize",
        400,
        "invalid_parameter",
    );
    let r = c.post_multipart(
        &format!("/v1/maps/{hog}/localize"),
        &[
            Part::image("q.png", route.query_png(0)),
            Part::json("params", &json!([4, null])),
        ],
    );
    expect(
        &r,
        "post",
        "/v1/maps/{id}/localize",
        400,
        "invalid_parameter",
    );
    assert!(r.message().contains("params"), "{}", r.message());
}
