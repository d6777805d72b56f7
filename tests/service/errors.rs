//! Every bad input gets a precise 4xx with the documented error shape, and a failed upload
//! writes nothing.

use serde_json::json;

use crate::common::{create_hog_map, create_vector_map, png, Route, Server};
use crate::http::{Client, Part};
use crate::spec::check;

const MAX_BODY: usize = 200_000;

pub(crate) fn strict_server() -> Server {
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

pub(crate) fn expect(
    r: &crate::http::Response,
    method: &str,
    template: &str,
    status: u16,
    code: &str,
) {
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
    // An empty filter is a malformed query, not a map that does not exist.
    let r = c.get("/v1/localizations?map=");
    expect(&r, "get", "/v1/localizations", 400, "invalid_parameter");
    assert!(r.message().contains("map"), "{}", r.message());
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
            // The estimated wait, or (before any turn was measured) the longest a queued
            // request may wait for a CPU (`--localize-max-wait-secs`, 30): never more.
            let retry: u64 = busy.header("retry-after").unwrap().parse().unwrap();
            assert!((1..=30).contains(&retry), "Retry-After {retry}");
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
