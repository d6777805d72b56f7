//! The reads that show maps and localizations to people: image metadata pages, thumbnails
//! stored at upload, the similarity picture stored with a localization, and a trip read from
//! a frame on (`?since=`). Generated images; every answer is checked against the OpenAPI.

use serde_json::json;

use crate::common::{create_hog_map, create_vector_map, Process, Route, Server};
use crate::http::{Client, Part, Response};
use crate::spec::check;

const IMAGES: &str = "/v1/maps/{id}/images";
const THUMB: &str = "/v1/maps/{id}/images/{index}/thumbnail";
const PICTURE: &str = "/v1/localizations/{id}/picture";
const TRIP: &str = "/v1/trips/{id}";

fn body(r: &Response) -> String {
    String::from_utf8_lossy(&r.body).into_owned()
}

fn references(route: &Route, range: std::ops::Range<u32>) -> Vec<Part> {
    range
        .map(|i| Part::image(&format!("r{i}.png"), route.reference_png(i)))
        .collect()
}

fn upload(c: &Client, map: &str, parts: &[Part]) -> Response {
    c.post_multipart(&format!("/v1/maps/{map}/images"), parts)
}

#[test]
fn thumbnails_are_stored_with_the_images_and_served() {
    let server = Server::start();
    let c = server.client;
    let route = Route::new(30, 3);
    let map = create_hog_map(&c, "thumbs", 8);

    // A batch with one broken image stores nothing: no descriptor and no thumbnail.
    let mut parts = references(&route, 0..3);
    parts.push(Part::image("broken.png", b"not a png".to_vec()));
    let r = upload(&c, &map, &parts);
    assert_eq!(r.status, 422, "{}", body(&r));
    let r = c.get(&format!("/v1/maps/{map}/images/0/thumbnail"));
    check("GET", THUMB, &r);
    assert_eq!((r.status, r.code().as_str()), (404, "thumbnail_not_found"));
    assert!(r.message().contains("has 0 images"), "{}", r.message());

    let r = upload(&c, &map, &references(&route, 0..20));
    assert_eq!(r.status, 200, "{}", body(&r));
    for i in [0u32, 7, 19] {
        let r = c.get(&format!("/v1/maps/{map}/images/{i}/thumbnail"));
        check("GET", THUMB, &r);
        assert_eq!(r.status, 200, "{}", body(&r));
        assert_eq!(r.header("content-type"), Some("image/jpeg"));
        assert!(r.header("cache-control").unwrap().contains("immutable"));
        // The thumbnail shows image i: a 64x32 frame is kept at its size, and its pixels are
        // those of the uploaded frame up to JPEG's loss.
        let thumb = image::load_from_memory(&r.body).unwrap().to_luma8();
        let original = image::load_from_memory(&route.reference_png(i))
            .unwrap()
            .to_luma8();
        assert_eq!(thumb.dimensions(), original.dimensions());
        let diff: f64 = thumb
            .pixels()
            .zip(original.pixels())
            .map(|(a, b)| f64::from(a[0].abs_diff(b[0])))
            .sum::<f64>()
            / f64::from(64 * 32);
        assert!(diff < 12.0, "image {i}: mean difference {diff}");
        let other = image::load_from_memory(&route.reference_png((i + 10) % 20))
            .unwrap()
            .to_luma8();
        let far: f64 = thumb
            .pixels()
            .zip(other.pixels())
            .map(|(a, b)| f64::from(a[0].abs_diff(b[0])))
            .sum::<f64>()
            / f64::from(64 * 32);
        assert!(
            far > diff * 2.0,
            "image {i} is not another image's thumbnail"
        );
    }
    let r = c.get(&format!("/v1/maps/{map}/images/20/thumbnail"));
    check("GET", THUMB, &r);
    assert_eq!((r.status, r.code().as_str()), (404, "thumbnail_not_found"));
    assert!(r.message().contains("has 20 images"), "{}", r.message());
    for bad in ["-1", "x", "4294967296"] {
        let r = c.get(&format!("/v1/maps/{map}/images/{bad}/thumbnail"));
        check("GET", THUMB, &r);
        assert_eq!(
            (r.status, r.code().as_str()),
            (400, "invalid_parameter"),
            "{bad}"
        );
    }
    let r = c.get("/v1/maps/00000000deadbeef/images/0/thumbnail");
    check("GET", THUMB, &r);
    assert_eq!((r.status, r.code().as_str()), (404, "map_not_found"));

    // Precomputed descriptors come without images, hence without thumbnails.
    let vectors = create_vector_map(&c, "vectors", 2);
    let r = c.post_json(
        &format!("/v1/maps/{vectors}/descriptors"),
        &json!({"descriptors": [[1.0, 0.0], [0.0, 1.0]]}),
    );
    assert_eq!(r.status, 200, "{}", body(&r));
    let r = c.get(&format!("/v1/maps/{vectors}/images/1/thumbnail"));
    assert_eq!((r.status, r.code().as_str()), (404, "thumbnail_not_found"));
    assert!(r.message().contains("no thumbnail"), "{}", r.message());

    // Deleting the map deletes its thumbnails.
    assert_eq!(c.delete(&format!("/v1/maps/{map}")).status, 204);
    let r = c.get(&format!("/v1/maps/{map}/images/0/thumbnail"));
    assert_eq!((r.status, r.code().as_str()), (404, "map_not_found"));
}

#[test]
fn image_metadata_is_read_page_by_page() {
    let server = Server::start();
    let c = server.client;
    let route = Route::new(30, 4);
    let map = create_hog_map(&c, "gps", 8);
    let metas: Vec<_> = (0..25)
        .map(|i| {
            if i == 3 {
                json!({})
            } else {
                json!({"latitude": 59.9 + f64::from(i) * 1e-3, "longitude": 10.7,
                       "timestamp": format!("t{i}"), "label": if i == 0 { "depot" } else { "" }})
            }
        })
        .collect();
    let mut parts = references(&route, 0..25);
    parts.push(Part::json("metadata", &json!(metas)));
    let r = upload(&c, &map, &parts);
    assert_eq!(r.status, 200, "{}", body(&r));

    let mut seen = Vec::new();
    let mut from = Some(0u64);
    while let Some(f) = from {
        let r = c.get(&format!("/v1/maps/{map}/images?from={f}&limit=10"));
        check("GET", IMAGES, &r);
        assert_eq!(r.status, 200, "{}", body(&r));
        let page = r.json();
        assert_eq!(page["image_count"], 25);
        seen.extend(page["items"].as_array().unwrap().clone());
        from = page["next"].as_u64();
    }
    assert_eq!(seen.len(), 25);
    for (i, m) in seen.iter().enumerate() {
        assert_eq!(m["index"], i);
        if i == 3 {
            assert!(m["latitude"].is_null() && m["timestamp"].is_null(), "{m}");
        } else {
            assert_eq!(m["latitude"], 59.9 + i as f64 * 1e-3);
            assert_eq!(m["timestamp"], format!("t{i}"));
        }
    }
    assert_eq!(seen[0]["label"], "depot");
    // Defaults and the end of the route.
    let r = c.get(&format!("/v1/maps/{map}/images"));
    assert_eq!(r.json()["items"].as_array().unwrap().len(), 25);
    assert!(r.json()["next"].is_null());
    let r = c.get(&format!("/v1/maps/{map}/images?from=99"));
    check("GET", IMAGES, &r);
    assert_eq!(r.status, 200);
    assert!(r.json()["items"].as_array().unwrap().is_empty() && r.json()["next"].is_null());
    for bad in ["limit=0", "limit=1001", "from=-1", "page=2"] {
        let r = c.get(&format!("/v1/maps/{map}/images?{bad}"));
        check("GET", IMAGES, &r);
        assert_eq!(
            (r.status, r.code().as_str()),
            (400, "invalid_parameter"),
            "{bad}"
        );
    }
    let r = c.get("/v1/maps/00000000deadbeef/images");
    check("GET", IMAGES, &r);
    assert_eq!((r.status, r.code().as_str()), (404, "map_not_found"));
}

#[test]
fn a_localization_keeps_its_similarity_picture() {
    let server = Server::start();
    let c = server.client;
    let route = Route::new(60, 5);
    let map = create_hog_map(&c, "picture", 8);
    assert_eq!(upload(&c, &map, &references(&route, 0..60)).status, 200);
    let queries: Vec<Part> = (20..40)
        .map(|i| Part::image(&format!("q{i}.png"), route.query_png(i)))
        .collect();
    let r = c.post_multipart(&format!("/v1/maps/{map}/localize"), &queries);
    assert_eq!(r.status, 200, "{}", body(&r));
    let loc = r.json();
    let picture = &loc["picture"];
    assert_eq!(
        (picture["rows"].as_u64(), picture["cols"].as_u64()),
        (Some(20), Some(60))
    );
    assert!(picture["hi"].as_f64().unwrap() > picture["lo"].as_f64().unwrap());
    let id = loc["id"].as_str().unwrap();
    let again = c.get(&format!("/v1/localizations/{id}"));
    assert_eq!(
        again.json(),
        loc,
        "the read-back equals the answer, picture included"
    );

    let r = c.get(&format!("/v1/localizations/{id}/picture"));
    check("GET", PICTURE, &r);
    assert_eq!(r.status, 200, "{}", body(&r));
    assert_eq!(r.header("content-type"), Some("image/png"));
    let png = image::load_from_memory(&r.body).unwrap().to_luma8();
    assert_eq!(
        png.dimensions(),
        (60, 20),
        "one pixel per cell at this size"
    );
    // Query k shows the place of reference 20 + k: that cell is among the brightest of its row.
    for k in 0..20u32 {
        let on = png.get_pixel(20 + k, k)[0];
        let mut row: Vec<u8> = (0..60).map(|j| png.get_pixel(j, k)[0]).collect();
        row.sort_unstable();
        assert!(on >= row[56], "query {k}: {on} vs row {row:?}");
    }

    let r = c.get("/v1/localizations/00000000deadbeef/picture");
    check("GET", PICTURE, &r);
    assert_eq!(
        (r.status, r.code().as_str()),
        (404, "localization_not_found")
    );
    // Deleting the map deletes the localization with its picture.
    assert_eq!(c.delete(&format!("/v1/maps/{map}")).status, 204);
    let r = c.get(&format!("/v1/localizations/{id}/picture"));
    assert_eq!(
        (r.status, r.code().as_str()),
        (404, "localization_not_found")
    );
}

#[test]
fn a_trip_is_read_from_a_frame_on() {
    let server = Server::start();
    let c = server.client;
    let route = Route::new(50, 6);
    let map = create_hog_map(&c, "since", 8);
    assert_eq!(upload(&c, &map, &references(&route, 0..50)).status, 200);
    let r = c.request("POST", &format!("/v1/maps/{map}/trips"), None, &[]);
    let trip = r.json()["id"].as_str().unwrap().to_string();
    for b in 0..4u32 {
        let parts: Vec<Part> = (b * 10..b * 10 + 10)
            .map(|i| Part::image(&format!("q{i}.png"), route.query_png(i)))
            .collect();
        let r = c.post_multipart(&format!("/v1/trips/{trip}/frames"), &parts);
        assert_eq!(r.status, 200, "{}", body(&r));
    }
    let all = c.get(&format!("/v1/trips/{trip}"));
    check("GET", TRIP, &all);
    let all = all.json()["estimates"].as_array().unwrap().clone();
    assert_eq!(all.len(), 40);
    let r = c.get(&format!("/v1/trips/{trip}?since=28"));
    check("GET", TRIP, &r);
    let tail = r.json();
    assert_eq!(tail["frame_count"], 40);
    assert_eq!(tail["estimates"].as_array().unwrap()[..], all[28..]);
    let r = c.get(&format!("/v1/trips/{trip}?since=40"));
    assert!(r.json()["estimates"].as_array().unwrap().is_empty());
    assert_eq!(
        c.get(&format!("/v1/trips/{trip}?since=0")).json()["estimates"]
            .as_array()
            .unwrap()[..],
        all[..]
    );
    for bad in ["since=-1", "since=x", "from=3"] {
        let r = c.get(&format!("/v1/trips/{trip}?{bad}"));
        check("GET", TRIP, &r);
        assert_eq!(
            (r.status, r.code().as_str()),
            (400, "invalid_parameter"),
            "{bad}"
        );
    }
}

#[test]
fn thumbnails_and_pictures_survive_a_sigkill() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let log = tmp.path().join("serve.log");
    let route = Route::new(20, 7);

    let p = Process::serve(&data, &log);
    let c = &p.client;
    let map = create_hog_map(c, "crash", 8);
    assert_eq!(upload(c, &map, &references(&route, 0..20)).status, 200);
    let queries: Vec<Part> = (5..15)
        .map(|i| Part::image(&format!("q{i}.png"), route.query_png(i)))
        .collect();
    let loc = c.post_multipart(&format!("/v1/maps/{map}/localize"), &queries);
    assert_eq!(loc.status, 200, "{}", body(&loc));
    let loc = loc.json()["id"].as_str().unwrap().to_string();
    let thumbs: Vec<Vec<u8>> = (0..20)
        .map(|i| c.get(&format!("/v1/maps/{map}/images/{i}/thumbnail")).body)
        .collect();
    let picture = c.get(&format!("/v1/localizations/{loc}/picture"));
    assert_eq!(picture.status, 200);
    // No chance to flush at shutdown: what was acknowledged must already be on disk.
    p.kill();

    let p = Process::serve(&data, &log);
    let c = &p.client;
    for (i, before) in thumbs.iter().enumerate() {
        let r = c.get(&format!("/v1/maps/{map}/images/{i}/thumbnail"));
        assert_eq!(r.status, 200, "thumbnail {i} after the kill: {}", body(&r));
        assert_eq!(&r.body, before, "thumbnail {i} changed");
    }
    let r = c.get(&format!("/v1/localizations/{loc}/picture"));
    assert_eq!(r.status, 200, "{}", body(&r));
    assert_eq!(r.body, picture.body);
    assert!(p.terminate());
}
