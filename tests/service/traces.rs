//! Traces over OTLP (issue 45): the real binary with `--otlp-endpoint` pointed at a small
//! OTLP/HTTP receiver this test runs on 127.0.0.1. The spans it receives: one server span per
//! request, named by its route template, a child of the caller's `traceparent`, with the ids
//! as attributes; the stages and the store calls as its children; and the response's
//! `traceparent` names the request's span.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::Value;

use crate::common::{Process, Route};
use crate::http::Part;

const TRACE: &str = "0af7651916cd43dd8448eb211c80319c";
const CALLER_SPAN: &str = "b7ad6b7169203331";

/// Accepts OTLP/HTTP JSON exports (`POST /v1/traces`) and keeps their bodies.
fn receiver() -> (u16, Arc<Mutex<Vec<Value>>>) {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let bodies = Arc::new(Mutex::new(Vec::new()));
    let kept = Arc::clone(&bodies);
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(stream) = stream else { continue };
            let kept = Arc::clone(&kept);
            std::thread::spawn(move || {
                let mut reader = BufReader::new(stream.try_clone().unwrap());
                let mut out = stream;
                // Requests on one kept-alive connection, until it closes.
                loop {
                    let mut length = 0usize;
                    let mut line = String::new();
                    let mut first = true;
                    loop {
                        line.clear();
                        if reader.read_line(&mut line).unwrap_or(0) == 0 {
                            return;
                        }
                        if first {
                            assert!(line.starts_with("POST /v1/traces "), "{line}");
                            first = false;
                        }
                        let l = line.trim_end();
                        if l.is_empty() {
                            break;
                        }
                        if let Some((k, v)) = l.split_once(':') {
                            if k.eq_ignore_ascii_case("content-length") {
                                length = v.trim().parse().unwrap();
                            }
                        }
                    }
                    let mut body = vec![0u8; length];
                    reader.read_exact(&mut body).unwrap();
                    kept.lock()
                        .unwrap()
                        .push(serde_json::from_slice(&body).unwrap());
                    let answer = "HTTP/1.1 200 OK\r\ncontent-type: application/json\r\n\
                                  content-length: 2\r\n\r\n{}";
                    if out.write_all(answer.as_bytes()).is_err() {
                        return;
                    }
                }
            });
        }
    });
    (port, bodies)
}

/// Every span received, flattened out of the export bodies.
fn spans(bodies: &[Value]) -> Vec<Value> {
    let mut out = Vec::new();
    for b in bodies {
        for rs in b["resourceSpans"].as_array().into_iter().flatten() {
            for ss in rs["scopeSpans"].as_array().into_iter().flatten() {
                out.extend(ss["spans"].as_array().into_iter().flatten().cloned());
            }
        }
    }
    out
}

/// The string value of attribute `key` of a span.
fn attribute<'a>(span: &'a Value, key: &str) -> Option<&'a str> {
    span["attributes"]
        .as_array()?
        .iter()
        .find(|a| a["key"] == key)?["value"]["stringValue"]
        .as_str()
}

#[test]
fn requests_are_traced_with_their_parent_their_ids_and_their_stages() {
    let (port, bodies) = receiver();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let endpoint = format!("http://127.0.0.1:{port}");
    let p = Process::start(
        &[
            "--addr",
            "127.0.0.1:0",
            "--data-dir",
            data.to_str().unwrap(),
            "--otlp-endpoint",
            &endpoint,
        ],
        &[],
        &dir.path().join("log"),
    );
    let c = &p.client;
    let traceparent = format!("00-{TRACE}-{CALLER_SPAN}-01");
    let body = serde_json::json!({"name": "traced", "descriptor": {"kind": "hog", "cell_size": 8}});
    let r = c.request_with(
        "POST",
        "/v1/maps",
        &[("traceparent", traceparent.as_str())],
        Some("application/json"),
        body.to_string().as_bytes(),
    );
    assert_eq!(r.status, 201);
    let map = r.json()["id"].as_str().unwrap().to_string();
    let answered = r
        .header("traceparent")
        .expect("no traceparent in the answer");
    assert!(answered.starts_with(&format!("00-{TRACE}-")), "{answered}");
    let request_span = answered.split('-').nth(2).unwrap().to_string();
    assert_ne!(request_span, CALLER_SPAN);

    let route = Route::new(20, 3);
    let parts: Vec<Part> = (0..20)
        .map(|i| Part::image(&format!("r{i}.png"), route.reference_png(i)))
        .collect();
    assert_eq!(
        c.post_multipart(&format!("/v1/maps/{map}/images"), &parts)
            .status,
        200
    );
    let r = c.request("POST", &format!("/v1/maps/{map}/trips"), None, &[]);
    assert_eq!(r.status, 201);
    let trip = r.json()["id"].as_str().unwrap().to_string();
    let parts: Vec<Part> = (0..10)
        .map(|i| Part::image(&format!("q{i}.png"), route.query_png(i)))
        .collect();
    let r = c.post_multipart(&format!("/v1/trips/{trip}/frames"), &parts);
    assert_eq!(r.status, 200);
    // SIGTERM: the service sends the spans still buffered before it exits.
    assert!(p.terminate());

    let deadline = Instant::now() + Duration::from_secs(10);
    let all = loop {
        let all = spans(&bodies.lock().unwrap());
        if all
            .iter()
            .any(|s| s["name"] == "POST /v1/trips/{id}/frames")
        {
            break all;
        }
        assert!(Instant::now() < deadline, "spans received: {all:#?}");
        std::thread::sleep(Duration::from_millis(100));
    };
    let named = |name: &str| -> Vec<&Value> { all.iter().filter(|s| s["name"] == name).collect() };
    // The create request: a child of the caller's span, in the caller's trace.
    let created = named("POST /v1/maps");
    let created = created
        .iter()
        .find(|s| s["traceId"] == TRACE)
        .unwrap_or_else(|| panic!("no span in trace {TRACE}: {created:#?}"));
    assert_eq!(created["parentSpanId"], CALLER_SPAN);
    assert_eq!(created["spanId"], request_span.as_str());
    assert_eq!(attribute(created, "route"), Some("/v1/maps"));
    let store = named("store");
    assert!(
        store
            .iter()
            .any(|s| s["parentSpanId"] == request_span.as_str()
                && attribute(s, "operation") == Some("create_map")),
        "no create_map store span under the request: {store:#?}"
    );
    // The frames request: its ids and its stages.
    let frames = named("POST /v1/trips/{id}/frames");
    let frames = frames[0];
    assert_eq!(attribute(frames, "trip_id"), Some(trip.as_str()));
    assert_eq!(attribute(frames, "route"), Some("/v1/trips/{id}/frames"));
    let id = frames["spanId"].as_str().unwrap();
    for stage in ["describe", "similarity", "solve", "store"] {
        assert!(
            named(stage)
                .iter()
                .any(|s| s["parentSpanId"] == id && s["traceId"] == frames["traceId"]),
            "no `{stage}` span under the frames request"
        );
    }
    assert!(named("store")
        .iter()
        .any(|s| s["parentSpanId"] == id && attribute(s, "operation") == Some("put_trip_batch")));
}
