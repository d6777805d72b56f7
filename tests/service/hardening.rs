//! Regression tests of what an outside attack test found (issue 12, "Hardening"): slow clients
//! are cut off, the localize queue is first come first served with a bounded wait, costs never
//! overflow to `null`, truncated JPEGs are refused, and new ids are random.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

use serde_json::json;

use crate::common::{create_hog_map, create_vector_map, Lcg, Route, Server};
use crate::http::{Client, Part};

/// Reads until the server closes the connection; fails if it stays open for `bound`.
fn read_until_closed(stream: &mut TcpStream, bound: Duration) -> Vec<u8> {
    stream.set_read_timeout(Some(bound)).unwrap();
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    loop {
        match stream.read(&mut buf) {
            Ok(0) => return got,
            Ok(n) => got.extend_from_slice(&buf[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                panic!(
                    "the server kept the connection open for {bound:?} (got {:?})",
                    String::from_utf8_lossy(&got)
                )
            }
            // A reset also closes the connection.
            Err(_) => return got,
        }
    }
}

#[test]
fn a_client_that_sends_half_a_header_is_disconnected() {
    let server = Server::start_with(|a| a.header_read_timeout_secs = 1);
    let mut slow = TcpStream::connect(server.client.addr).unwrap();
    slow.write_all(b"GET /v1/maps HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
        .unwrap();
    // Well above the 1 s bound (a generous margin for a loaded machine), well below forever.
    let answer = read_until_closed(&mut slow, Duration::from_secs(20));
    assert!(
        !answer.starts_with(b"HTTP/1.1 200"),
        "{}",
        String::from_utf8_lossy(&answer)
    );
    // An idle connection that never sends a byte is closed the same way.
    let mut idle = TcpStream::connect(server.client.addr).unwrap();
    read_until_closed(&mut idle, Duration::from_secs(20));
    // Normal clients are unaffected.
    assert_eq!(server.client.get("/v1/maps").status, 200);
}

#[test]
fn a_body_that_stalls_gets_408_and_the_connection_closes() {
    let server = Server::start_with(|a| a.body_read_timeout_secs = 1);
    let mut slow = TcpStream::connect(server.client.addr).unwrap();
    slow.write_all(
        b"POST /v1/maps HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n\
          Content-Length: 200\r\n\r\n{\"name\": \"slo",
    )
    .unwrap();
    let answer = read_until_closed(&mut slow, Duration::from_secs(20));
    let text = String::from_utf8_lossy(&answer);
    assert!(text.starts_with("HTTP/1.1 408"), "{text}");
    assert!(text.contains("\"body_timeout\""), "{text}");
    // Nothing was created.
    let maps = server.client.get("/v1/maps").json();
    assert_eq!(maps["maps"].as_array().map(Vec::len), Some(0), "{maps}");
}

/// A precomputed map of `refs` random `dim`-long descriptors.
fn vector_map(client: &Client, refs: usize, dim: usize, seed: u64) -> String {
    let id = create_vector_map(client, "v", dim as u32);
    let rows = random_rows(refs, dim, seed);
    let r = client.post_json(
        &format!("/v1/maps/{id}/descriptors"),
        &json!({ "descriptors": rows }),
    );
    assert_eq!(r.status, 200, "{}", r.message());
    id
}

fn random_rows(n: usize, dim: usize, seed: u64) -> Vec<Vec<f64>> {
    let mut rng = Lcg::new(seed);
    (0..n)
        .map(|_| {
            (0..dim)
                .map(|_| f64::from(rng.below(1000)) / 1000.0)
                .collect()
        })
        .collect()
}

fn metric(client: &Client, name: &str) -> u64 {
    let text = String::from_utf8(client.get("/metrics").body).unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix(&format!("{name} ")))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no {name} in /metrics"))
}

#[test]
fn localizations_are_admitted_in_arrival_order() {
    // One CPU turn at a time: turns end, and results are stored, in the order they began.
    let server = Server::start_with(|a| {
        a.worker_threads = 1;
        a.localize_queue = 64;
    });
    let client = server.client;
    let map = vector_map(&client, 600, 64, 1);
    let n = 10;
    let mut handles = Vec::new();
    for i in 0..n {
        // Request i is told apart by its query count.
        let body = json!({ "descriptors": random_rows(40 + i, 64, 100 + i as u64) });
        let path = format!("/v1/maps/{map}/localize");
        handles.push(std::thread::spawn(move || client.post_json(&path, &body)));
        // Send the next one only once this one has asked for its turn.
        let deadline = Instant::now() + Duration::from_secs(60);
        while metric(&client, "seasonloc_localize_arrivals_total") < i as u64 + 1 {
            assert!(
                Instant::now() < deadline,
                "request {i} never reached the queue"
            );
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    for h in handles {
        let r = h.join().unwrap();
        assert_eq!(r.status, 200, "{}", r.message());
    }
    let listed = client.get(&format!("/v1/localizations?map={map}&limit=100"));
    let mut counts: Vec<u64> = listed.json()["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["query_count"].as_u64().unwrap())
        .collect();
    counts.reverse(); // listed newest first
    let sent: Vec<u64> = (0..n as u64).map(|i| 40 + i).collect();
    assert_eq!(counts, sent);
}

#[test]
fn under_a_burst_no_admitted_localization_times_out() {
    // Far more requests than one CPU serves within the 1 s bound on waiting: each is either
    // served or refused with 503 `queue_full` + Retry-After (at once, or after at most the
    // bound) — never admitted and then cut off by the 30 s request timeout.
    let server = Server::start_with(|a| {
        a.worker_threads = 1;
        a.localize_queue = 8;
        a.localize_max_wait_secs = 1;
        a.request_timeout_secs = 30;
    });
    let client = server.client;
    let map = vector_map(&client, 2000, 128, 2);
    let body = json!({ "descriptors": random_rows(200, 128, 3) });
    let path = format!("/v1/maps/{map}/localize");
    // Warm up: the queue learns how long a turn takes.
    assert_eq!(client.post_json(&path, &body).status, 200);
    let handles: Vec<_> = (0..24)
        .map(|_| {
            let (path, body) = (path.clone(), body.clone());
            std::thread::spawn(move || client.post_json(&path, &body))
        })
        .collect();
    let mut served = 0;
    let mut refused = 0;
    for h in handles {
        let r = h.join().unwrap();
        match r.status {
            200 => served += 1,
            503 => {
                assert_eq!(r.code(), "queue_full", "{}", r.message());
                let retry: u64 = r.header("retry-after").unwrap().parse().unwrap();
                assert!(retry >= 1);
                refused += 1;
            }
            s => panic!("unexpected {s}: {}", r.message()),
        }
    }
    assert!(served >= 1, "{served} served, {refused} refused");
    let rejected = metric(&client, "seasonloc_localize_rejected_total");
    assert_eq!(rejected, refused);
}

#[test]
fn hidden_costs_are_bounded_so_costs_never_overflow_to_null() {
    let server = Server::start();
    let client = server.client;
    let map = vector_map(&client, 30, 8, 4);
    let queries = random_rows(12, 8, 5);
    let path = format!("/v1/maps/{map}/localize");
    // 1e308 with 8 flows once summed to infinity, sent as `null`: now refused up front.
    let r = client.post_json(
        &path,
        &json!({"descriptors": queries, "params": {"hidden_cost": 1e308, "flows": 8}}),
    );
    assert_eq!(r.status, 400, "{}", r.message());
    assert_eq!(r.code(), "invalid_parameter");
    assert!(r.message().contains("hidden_cost"), "{}", r.message());
    // The largest accepted value gives finite costs.
    let r = client.post_json(
        &path,
        &json!({"descriptors": queries, "params": {"hidden_cost": 1e12, "flows": 8}}),
    );
    assert_eq!(r.status, 200, "{}", r.message());
    let doc = r.json();
    assert!(
        doc["total_cost"].as_f64().is_some_and(f64::is_finite),
        "{doc}"
    );
    for h in doc["hypotheses"].as_array().unwrap() {
        assert!(h["cost"].as_f64().is_some_and(f64::is_finite), "{h}");
    }
    // Trips share the bound.
    let hog = create_hog_map(&client, "h", 8);
    let route = Route::new(6, 9);
    let parts: Vec<Part> = (0..6)
        .map(|i| Part::image(&format!("r{i}.png"), route.reference_png(i)))
        .collect();
    assert_eq!(
        client
            .post_multipart(&format!("/v1/maps/{hog}/images"), &parts)
            .status,
        200
    );
    let r = client.post_json(
        &format!("/v1/maps/{hog}/trips"),
        &json!({"hidden_cost": 1e300}),
    );
    assert_eq!(r.status, 400, "{}", r.message());
    assert!(r.message().contains("hidden_cost"), "{}", r.message());
}

#[test]
fn new_ids_are_random_and_still_list_newest_first() {
    let server = Server::start();
    let client = server.client;
    let ids: Vec<String> = (0..6)
        .map(|i| create_vector_map(&client, &format!("m{i}"), 2))
        .collect();
    let numbers: Vec<u64> = ids
        .iter()
        .map(|id| {
            assert!(
                id.len() == 16 && id.bytes().all(|b| b.is_ascii_hexdigit()),
                "{id}"
            );
            u64::from_str_radix(id, 16).unwrap()
        })
        .collect();
    // Not a counter: no id is its predecessor plus one, and they are not small.
    assert!(numbers.windows(2).all(|w| w[1] > w[0] + 1), "{numbers:x?}");
    assert!(numbers.iter().all(|&n| n > 1 << 40), "{numbers:x?}");
    // Maps list oldest first, localizations newest first, as before.
    let listed: Vec<String> = client.get("/v1/maps").json()["maps"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["id"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(listed, ids);
    let map = &ids[0];
    let r = client.post_json(
        &format!("/v1/maps/{map}/descriptors"),
        &json!({"descriptors": [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]}),
    );
    assert_eq!(r.status, 200, "{}", r.message());
    let mut made = Vec::new();
    for _ in 0..3 {
        let r = client.post_json(
            &format!("/v1/maps/{map}/localize"),
            &json!({"descriptors": [[1.0, 0.1], [0.1, 1.0]]}),
        );
        assert_eq!(r.status, 200, "{}", r.message());
        made.push(r.json()["id"].as_str().unwrap().to_string());
    }
    let page = client.get("/v1/localizations?limit=2").json();
    let first: Vec<&str> = page["items"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["id"].as_str().unwrap())
        .collect();
    assert_eq!(first, vec![made[2].as_str(), made[1].as_str()]);
    let next = page["next"].as_str().unwrap();
    let rest = client
        .get(&format!("/v1/localizations?limit=2&before={next}"))
        .json();
    assert_eq!(rest["items"][0]["id"], made[0].as_str());
    assert!(rest["next"].is_null(), "{rest}");
}

#[test]
fn truncated_jpegs_are_refused_and_nothing_is_stored() {
    let server = Server::start();
    let client = server.client;
    let map = create_hog_map(&client, "j", 8);
    let route = Route::new(4, 11);
    let jpeg = |i: u32| {
        let img = image::load_from_memory(&route.reference_png(i))
            .unwrap()
            .to_luma8();
        let mut out = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 90)
            .encode_image(&img)
            .unwrap();
        out
    };
    let whole = jpeg(1);
    let cut = whole[..whole.len() / 2].to_vec();
    let r = client.post_multipart(
        &format!("/v1/maps/{map}/images"),
        &[
            Part::image("a.jpg", jpeg(0)),
            Part::image("b.jpg", cut.clone()),
        ],
    );
    assert_eq!(r.status, 422, "{}", r.message());
    assert_eq!(r.code(), "invalid_image");
    assert!(r.message().contains("image[1]"), "{}", r.message());
    // The batch was refused whole: the map is still empty.
    let m = client.get(&format!("/v1/maps/{map}")).json();
    assert_eq!(m["image_count"], 0, "{m}");
    // With whole images the same batch is stored.
    let parts: Vec<Part> = (0..4)
        .map(|i| Part::image(&format!("{i}.jpg"), jpeg(i)))
        .collect();
    let r = client.post_multipart(&format!("/v1/maps/{map}/images"), &parts);
    assert_eq!(r.status, 200, "{}", r.message());
    // A truncated query is refused too, and no result is stored.
    let r = client.post_multipart(
        &format!("/v1/maps/{map}/localize"),
        &[Part::image("q.jpg", cut)],
    );
    assert_eq!(r.status, 422, "{}", r.message());
    assert_eq!(r.code(), "invalid_image");
    let listed = client.get("/v1/localizations").json();
    assert_eq!(
        listed["items"].as_array().map(Vec::len),
        Some(0),
        "{listed}"
    );
}
