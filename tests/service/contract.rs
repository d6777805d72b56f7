//! The document's statements about requests are the server's: every numeric bound it states
//! is where the server starts refusing, and every optional field takes `null`.

use serde_json::json;

use crate::common::{create_hog_map, create_vector_map, Route};
use crate::errors::{expect, strict_server};
use crate::http::Part;
use crate::spec::check;

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
    use seasonloc_core::features::hog::{MAX_CELL_SIZE, MIN_CELL_SIZE};
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

    use seasonloc_core::features::cnn::{MAX_INPUT_SIDE, MAX_SHORT_SIDE};
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
        Some(seasonloc_core::cooc::model::MAX_LOCATIONS as u64 - 1)
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
    // What is not JSON at all is malformed JSON, whatever its first byte.
    for (path, body) in [
        ("/v1/maps", "notjson"),
        ("/v1/maps", r#"{"name": "x", "#),
        (trips.as_str(), "notjson"),
    ] {
        let r = c.request("POST", path, Some("application/json"), body.as_bytes());
        assert_eq!(
            (r.status, r.code().as_str()),
            (400, "bad_request"),
            "{body}"
        );
        assert!(
            r.message().contains("malformed JSON"),
            "{body}: {}",
            r.message()
        );
    }
    // An empty or broken `params` part is named as the part, not as "the body".
    let localize_images = format!("/v1/maps/{hog}/localize");
    for params in [&b""[..], b"notjson"] {
        let parts = [
            Part::image("q.png", route.query_png(0)),
            Part {
                bytes: params.to_vec(),
                ..Part::json("params", &json!({}))
            },
        ];
        let r = c.post_multipart(&localize_images, &parts);
        assert_eq!((r.status, r.code().as_str()), (400, "bad_request"));
        assert!(r.message().contains("`params`"), "{}", r.message());
    }

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
