//! Access control end to end: every role against every route (401 vs 403), a real map's life
//! cycle by role, per-key in-flight cap, CORS preflights, the `Host` check, key rotation on
//! SIGHUP with the real binary (and no key in its log), and the refusal to serve a public
//! address without keys.

use std::io::{Read, Write};
use std::path::Path;
use std::time::{Duration, Instant};

use serde_json::json;
use sha2::{Digest, Sha256};

use crate::common::{Process, Route, Server};
use crate::http::{multipart_body, Client, Part, Response, BOUNDARY};
use crate::spec;

const ADMIN: &str = "adm-5f0c2b9e7d114a83";
const VEHICLE: &str = "veh-a81d3c4e2f6b0975";
const READER: &str = "rd-0e9f8a7b6c5d4e3f";

fn sha(key: &str) -> String {
    Sha256::digest(key.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

fn key_file(keys: &[(&str, &str, &str)]) -> String {
    let keys: Vec<_> = keys
        .iter()
        .map(|(name, role, key)| json!({"name": name, "role": role, "sha256": sha(key)}))
        .collect();
    json!({ "keys": keys }).to_string()
}

fn write_keys(path: &Path) {
    std::fs::write(
        path,
        key_file(&[
            ("ops", "admin", ADMIN),
            ("car-7", "vehicle", VEHICLE),
            ("wall", "reader", READER),
        ]),
    )
    .unwrap();
}

/// A server with the three keys above.
fn keyed_server(
    configure: impl FnOnce(&mut seasonloc_server::config::ServeArgs),
) -> (Server, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("keys.json");
    write_keys(&path);
    let server = Server::start_with(|a| {
        a.api_keys = Some(path.clone());
        configure(a);
    });
    (server, dir)
}

fn bearer(key: &str) -> String {
    format!("Bearer {key}")
}

fn call(
    c: &Client,
    method: &str,
    path: &str,
    key: Option<&str>,
    ct: Option<&str>,
    body: &[u8],
) -> Response {
    let auth = key.map(bearer);
    let headers: Vec<(&str, &str)> = auth.iter().map(|a| ("Authorization", a.as_str())).collect();
    c.request_with(method, path, &headers, ct, body)
}

/// Who may call each route, written out independently of the server's rule table.
/// `None` = public; otherwise the least role that may.
const TABLE: &[(&str, &str, Option<&str>)] = &[
    ("post", "/v1/maps", Some("admin")),
    ("get", "/v1/maps", Some("reader")),
    ("get", "/v1/maps/{id}", Some("reader")),
    ("delete", "/v1/maps/{id}", Some("admin")),
    ("post", "/v1/maps/{id}/images", Some("admin")),
    ("get", "/v1/maps/{id}/images", Some("reader")),
    (
        "get",
        "/v1/maps/{id}/images/{index}/thumbnail",
        Some("reader"),
    ),
    ("post", "/v1/maps/{id}/descriptors", Some("admin")),
    ("post", "/v1/maps/{id}/drives", Some("admin")),
    ("post", "/v1/maps/{id}/localize", Some("vehicle")),
    ("get", "/v1/localizations", Some("reader")),
    ("get", "/v1/localizations/{id}", Some("reader")),
    ("get", "/v1/localizations/{id}/picture", Some("reader")),
    ("post", "/v1/maps/{id}/trips", Some("vehicle")),
    ("get", "/v1/maps/{id}/trips", Some("reader")),
    ("post", "/v1/trips/{id}/frames", Some("vehicle")),
    ("get", "/v1/trips/{id}", Some("reader")),
    ("post", "/v1/trips/{id}/close", Some("vehicle")),
    ("get", "/healthz", None),
    ("get", "/readyz", None),
    ("get", "/metrics", Some("reader")),
    ("get", "/openapi.json", None),
    ("get", "/", None),
    ("get", "/maps/{id}", None),
    ("get", "/localizations/{id}", None),
    ("get", "/trips/{id}", None),
    ("get", "/assets/{name}", None),
];

fn rank(role: &str) -> u8 {
    match role {
        "reader" => 1,
        "vehicle" => 2,
        "admin" => 3,
        other => panic!("role {other}"),
    }
}

#[test]
fn every_role_against_every_route() {
    let mut table: Vec<(String, String)> = TABLE
        .iter()
        .map(|(m, p, _)| (m.to_string(), p.to_string()))
        .collect();
    table.sort();
    let mut routes: Vec<(String, String)> = seasonloc_server::api::ROUTES
        .iter()
        .map(|(m, p)| (m.to_string(), p.to_string()))
        .collect();
    routes.sort();
    assert_eq!(table, routes, "the table must list every route");

    let (server, _dir) = keyed_server(|_| {});
    let c = server.client;
    let callers: [(&str, Option<&str>); 5] = [
        ("anonymous", None),
        ("unknown", Some("not-a-key")),
        ("reader", Some(READER)),
        ("vehicle", Some(VEHICLE)),
        ("admin", Some(ADMIN)),
    ];
    for (method, template, needs) in TABLE {
        // Ids that do not exist: allowed calls answer 404/400/..., never touching data.
        let path = template
            .replace("{id}", "00000000ffffffff")
            .replace("{index}", "0")
            .replace("{name}", "app.js");
        for (who, key) in callers {
            let r = call(
                &c,
                &method.to_ascii_uppercase(),
                &path,
                key,
                Some("application/json"),
                b"{}",
            );
            let what = format!(
                "{who} {method} {path}: {} {}",
                r.status,
                String::from_utf8_lossy(&r.body)
            );
            match needs {
                None => assert!(
                    r.status != 401 && r.status != 403,
                    "public route refused: {what}"
                ),
                Some(role) => match key {
                    Some(k) if k != "not-a-key" && rank(who) >= rank(role) => {
                        assert!(
                            r.status != 401 && r.status != 403,
                            "allowed call refused: {what}"
                        )
                    }
                    Some(k) if k != "not-a-key" => {
                        assert_eq!((r.status, r.code().as_str()), (403, "forbidden"), "{what}");
                        assert!(r.message().contains(role), "{what}");
                    }
                    _ => {
                        assert_eq!(
                            (r.status, r.code().as_str()),
                            (401, "unauthorized"),
                            "{what}"
                        );
                        assert!(
                            r.header("www-authenticate")
                                .is_some_and(|v| v.starts_with("Bearer")),
                            "{what}"
                        );
                    }
                },
            }
            spec::check(method, template, &r);
        }
    }
    // Unknown routes need a key too, so anonymous callers learn nothing from a 404.
    let r = call(&c, "GET", "/v1/nothing-here", None, None, b"");
    assert_eq!(r.status, 401);
    let r = call(&c, "GET", "/v1/nothing-here", Some(READER), None, b"");
    assert_eq!((r.status, r.code().as_str()), (404, "route_not_found"));
}

#[test]
fn bearer_parsing_is_strict_about_the_key_and_lenient_about_the_scheme() {
    let (server, _dir) = keyed_server(|_| {});
    let c = server.client;
    let get = |auth: &str| c.request_with("GET", "/v1/maps", &[("Authorization", auth)], None, b"");
    assert_eq!(get(&format!("Bearer {READER}")).status, 200);
    assert_eq!(get(&format!("bearer {READER}")).status, 200);
    assert_eq!(
        get(&format!("Bearer {}", &READER[..READER.len() - 1])).status,
        401
    );
    assert_eq!(get(&format!("Bearer {READER}x")).status, 401);
    assert_eq!(get(&format!("Basic {READER}")).status, 401);
    assert_eq!(get(READER).status, 401);
    assert_eq!(get("Bearer ").status, 401);
    assert_eq!(
        get(&format!("Bearer {}", sha(READER))).status,
        401,
        "the digest is not a key"
    );
}

#[test]
fn a_map_life_cycle_by_role() {
    let (server, _dir) = keyed_server(|_| {});
    let c = server.client;
    let route = Route::new(12, 7);
    let create = json!({"name": "r", "descriptor": {"kind": "hog", "cell_size": 8}}).to_string();
    for key in [READER, VEHICLE] {
        let r = call(
            &c,
            "POST",
            "/v1/maps",
            Some(key),
            Some("application/json"),
            create.as_bytes(),
        );
        assert_eq!((r.status, r.code().as_str()), (403, "forbidden"));
    }
    let r = call(
        &c,
        "POST",
        "/v1/maps",
        Some(ADMIN),
        Some("application/json"),
        create.as_bytes(),
    );
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let map = r.json()["id"].as_str().unwrap().to_string();
    let ct = format!("multipart/form-data; boundary={BOUNDARY}");
    let refs: Vec<Part> = (0..12)
        .map(|i| Part::image(&format!("r{i}.png"), route.reference_png(i)))
        .collect();
    let refs = multipart_body(&refs);
    let images = format!("/v1/maps/{map}/images");
    assert_eq!(
        call(&c, "POST", &images, Some(VEHICLE), Some(&ct), &refs).status,
        403
    );
    let r = call(&c, "POST", &images, Some(ADMIN), Some(&ct), &refs);
    assert!(r.status < 300, "{}", String::from_utf8_lossy(&r.body));
    let queries: Vec<Part> = (3..9)
        .map(|i| Part::image(&format!("q{i}.png"), route.query_png(i)))
        .collect();
    let queries = multipart_body(&queries);
    let localize = format!("/v1/maps/{map}/localize");
    assert_eq!(
        call(&c, "POST", &localize, Some(READER), Some(&ct), &queries).status,
        403
    );
    let r = call(&c, "POST", &localize, Some(VEHICLE), Some(&ct), &queries);
    assert!(r.status < 300, "{}", String::from_utf8_lossy(&r.body));
    let loc = r.json()["id"].as_str().unwrap().to_string();
    let r = call(
        &c,
        "GET",
        &format!("/v1/localizations/{loc}"),
        Some(READER),
        None,
        b"",
    );
    assert_eq!(r.status, 200);
    let trips = format!("/v1/maps/{map}/trips");
    assert_eq!(
        call(
            &c,
            "POST",
            &trips,
            Some(READER),
            Some("application/json"),
            b"{}"
        )
        .status,
        403
    );
    let r = call(
        &c,
        "POST",
        &trips,
        Some(VEHICLE),
        Some("application/json"),
        b"{}",
    );
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let trip = r.json()["id"].as_str().unwrap().to_string();
    let frames = format!("/v1/trips/{trip}/frames");
    assert_eq!(
        call(&c, "POST", &frames, Some(READER), Some(&ct), &queries).status,
        403
    );
    assert_eq!(
        call(&c, "POST", &frames, Some(VEHICLE), Some(&ct), &queries).status,
        200
    );
    let r = call(
        &c,
        "GET",
        &format!("/v1/trips/{trip}"),
        Some(READER),
        None,
        b"",
    );
    assert_eq!(r.json()["frame_count"], 6);
    let close = format!("/v1/trips/{trip}/close");
    assert_eq!(
        call(&c, "POST", &close, Some(READER), None, b"").status,
        403
    );
    assert_eq!(
        call(&c, "POST", &close, Some(VEHICLE), None, b"").status,
        200
    );
    let map_path = format!("/v1/maps/{map}");
    for key in [READER, VEHICLE] {
        assert_eq!(
            call(&c, "DELETE", &map_path, Some(key), None, b"").status,
            403
        );
    }
    assert_eq!(
        call(&c, "GET", &map_path, Some(READER), None, b"").json()["image_count"],
        12
    );
    // The key's name labels the metrics.
    let metrics =
        String::from_utf8(call(&c, "GET", "/metrics", Some(READER), None, b"").body).unwrap();
    assert!(
        metrics.contains("seasonloc_http_requests_by_key_total{key=\"car-7\",status=\"403\"}"),
        "{metrics}"
    );
    assert!(!metrics.contains(VEHICLE) && !metrics.contains(&sha(VEHICLE)));
    assert_eq!(
        call(&c, "DELETE", &map_path, Some(ADMIN), None, b"").status,
        204
    );
}

#[test]
fn a_key_with_its_requests_in_flight_gets_429_and_others_do_not() {
    let (server, _dir) = keyed_server(|a| a.max_requests_per_key = 1);
    let c = server.client;
    // A request whose body never finishes holds the key's only slot: sent while no other
    // request of the key is in flight, and once it is answered nothing (it was admitted and is
    // waiting for its body) rather than refused.
    let mut slow = loop {
        let mut s = std::net::TcpStream::connect(c.addr).unwrap();
        write!(
            s,
            "POST /v1/maps HTTP/1.1\r\nHost: x\r\nConnection: close\r\nAuthorization: Bearer {ADMIN}\r\n\
             Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{{\"name\""
        )
        .unwrap();
        s.flush().unwrap();
        s.set_read_timeout(Some(Duration::from_millis(300)))
            .unwrap();
        let mut first = [0u8; 1];
        match s.read(&mut first) {
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                s.set_read_timeout(None).unwrap();
                break s;
            }
            _ => continue,
        }
    };
    let deadline = Instant::now() + Duration::from_secs(10);
    let r = loop {
        let r = call(&c, "GET", "/v1/maps", Some(ADMIN), None, b"");
        if r.status == 429 || Instant::now() > deadline {
            break r;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    assert_eq!((r.status, r.code().as_str()), (429, "too_many_requests"));
    assert_eq!(r.header("retry-after"), Some("1"));
    spec::check("get", "/v1/maps", &r);
    assert_eq!(
        call(&c, "GET", "/v1/maps", Some(READER), None, b"").status,
        200
    );
    // Finishing the slow request frees the slot.
    write!(slow, "{}", " ".repeat(93)).unwrap();
    let mut rest = Vec::new();
    let _ = slow.read_to_end(&mut rest);
    assert_eq!(
        call(&c, "GET", "/v1/maps", Some(ADMIN), None, b"").status,
        200
    );
}

#[test]
fn cors_preflights_follow_the_allow_list() {
    let (server, _dir) = keyed_server(|a| a.cors_origins = vec!["https://ops.example.com".into()]);
    let c = server.client;
    let preflight = |origin: &str| {
        c.request_with(
            "OPTIONS",
            "/v1/maps",
            &[
                ("Origin", origin),
                ("Access-Control-Request-Method", "POST"),
                (
                    "Access-Control-Request-Headers",
                    "authorization,content-type",
                ),
            ],
            None,
            b"",
        )
    };
    let r = preflight("https://ops.example.com");
    assert_eq!(r.status, 200, "a preflight needs no key");
    assert_eq!(
        r.header("access-control-allow-origin"),
        Some("https://ops.example.com")
    );
    assert!(r
        .header("access-control-allow-headers")
        .is_some_and(|h| h.to_ascii_lowercase().contains("authorization")));
    let r = preflight("https://evil.example.net");
    assert!(
        r.header("access-control-allow-origin").is_none(),
        "{:?}",
        r.headers
    );
    let r = c.request_with(
        "GET",
        "/v1/maps",
        &[
            ("Origin", "https://ops.example.com"),
            ("Authorization", &bearer(READER)),
        ],
        None,
        b"",
    );
    assert_eq!(r.status, 200);
    assert_eq!(
        r.header("access-control-allow-origin"),
        Some("https://ops.example.com")
    );
}

#[test]
fn unexpected_host_headers_are_refused_when_configured() {
    let (server, _dir) = keyed_server(|a| a.allowed_hosts = vec!["seasonloc.internal".into()]);
    let c = server.client;
    let auth = bearer(READER);
    let get = |path: &str, host: &str| {
        c.request_with(
            "GET",
            path,
            &[("Host", host), ("Authorization", &auth)],
            None,
            b"",
        )
    };
    let r = get("/v1/maps", "attacker.example:8080");
    assert_eq!((r.status, r.code().as_str()), (421, "misdirected_request"));
    spec::check("get", "/v1/maps", &r);
    assert_eq!(get("/", "attacker.example").status, 421);
    assert_eq!(get("/v1/maps", "seasonloc.internal").status, 200);
    assert_eq!(get("/v1/maps", "SeasonLoc.Internal:8080").status, 200);
    assert_eq!(
        get("/healthz", "10.0.0.7:8080").status,
        200,
        "probes answer any host"
    );
}

fn hup(p: &Process) {
    let ok = std::process::Command::new("sh")
        .args(["-c", &format!("kill -HUP {}", p.child.id())])
        .status()
        .unwrap();
    assert!(ok.success());
}

fn wait_status(c: &Client, key: &str, want: u16) {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let r = call(c, "GET", "/v1/maps", Some(key), None, b"");
        if r.status == want {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "still {} (want {want})",
            r.status
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn sighup_rotates_keys_and_a_bad_file_keeps_the_old_ones() {
    let dir = tempfile::tempdir().unwrap();
    let keys = dir.path().join("keys.json");
    let log = dir.path().join("serve.log");
    std::fs::write(&keys, key_file(&[("old-key", "admin", "k-old-1234")])).unwrap();
    let data = dir.path().join("data");
    let p = Process::start(
        &[
            "--addr",
            "127.0.0.1:0",
            "--data-dir",
            data.to_str().unwrap(),
        ],
        &[("SEASONLOC_API_KEYS", keys.to_str().unwrap())],
        &log,
    );
    let c = p.client;
    assert_eq!(
        call(&c, "GET", "/v1/maps", Some("k-old-1234"), None, b"").status,
        200
    );
    assert_eq!(
        call(&c, "GET", "/v1/maps", Some("k-new-5678"), None, b"").status,
        401
    );

    std::fs::write(&keys, key_file(&[("new-key", "reader", "k-new-5678")])).unwrap();
    hup(&p);
    wait_status(&c, "k-new-5678", 200);
    assert_eq!(
        call(&c, "GET", "/v1/maps", Some("k-old-1234"), None, b"").status,
        401
    );
    let create = json!({"name": "x", "descriptor": {"kind": "hog"}}).to_string();
    let r = call(
        &c,
        "POST",
        "/v1/maps",
        Some("k-new-5678"),
        Some("application/json"),
        create.as_bytes(),
    );
    assert_eq!(r.status, 403, "the new file's role applies");

    std::fs::write(&keys, "{\"keys\": [ torn").unwrap();
    hup(&p);
    let deadline = Instant::now() + Duration::from_secs(20);
    while !std::fs::read_to_string(&log)
        .unwrap()
        .contains("keeping the previous API keys")
    {
        assert!(
            Instant::now() < deadline,
            "no log line for the bad key file"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(
        call(&c, "GET", "/v1/maps", Some("k-new-5678"), None, b"").status,
        200
    );
    assert!(p.terminate());
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(
        text.contains("key=\"new-key\""),
        "the key's name is in the request log:\n{text}"
    );
    for secret in ["k-old-1234", "k-new-5678"] {
        assert!(!text.contains(secret), "a key leaked into the log:\n{text}");
    }
}

#[test]
fn a_public_address_without_keys_is_refused_in_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_seasonloc"))
        .args(["serve", "--addr", "0.0.0.0:0", "--data-dir"])
        .arg(dir.path().join("data"))
        .env_remove("SEASONLOC_API_KEYS")
        .env_remove("SEASONLOC_ALLOW_UNAUTHENTICATED")
        .env_remove("SEASONLOC_ADDR")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(
        err.contains("--api-keys") && err.contains("--allow-unauthenticated"),
        "{err}"
    );
    assert!(!dir.path().join("data").exists(), "nothing was created");
}

#[test]
fn a_missing_or_bad_key_file_stops_start_up() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("keys.json");
    std::fs::write(
        &bad,
        r#"{"keys": [{"name": "a", "role": "superuser", "sha256": "00"}]}"#,
    )
    .unwrap();
    for file in [bad.clone(), dir.path().join("missing.json")] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_seasonloc"))
            .args(["serve", "--addr", "127.0.0.1:0", "--data-dir"])
            .arg(dir.path().join("data"))
            .arg("--api-keys")
            .arg(&file)
            .output()
            .unwrap();
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("API key file"), "{err}");
        // Checked before the store is opened: no data folder, no migration.
        assert!(!dir.path().join("data").exists(), "{err}");
        assert!(!err.contains("store layout upgraded"), "{err}");
    }
}

#[test]
fn cnn_models_come_only_from_the_model_directory() {
    let models = tempfile::tempdir().unwrap();
    std::fs::create_dir(models.path().join("sub")).unwrap();
    let fifo = models.path().join("fifo.onnx");
    let have_fifo = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .is_ok_and(|s| s.success());
    let dir = models.path().to_path_buf();
    let server = Server::start_with(move |a| a.model_dir = Some(dir));
    let c = server.client;
    let create = |model: &str| {
        let r = c.post_json(
            "/v1/maps",
            &json!({"name": "m", "descriptor": {"kind": "cnn", "model": model, "layer": "pooled"}}),
        );
        spec::check("post", "/v1/maps", &r);
        r
    };
    let mut hostile = vec![
        "/dev/zero".to_string(),
        "/proc/self/fd/2".to_string(),
        "/etc/passwd".to_string(),
        "../../etc/passwd".to_string(),
        "absent.onnx".to_string(),
        "sub".to_string(),
        models.path().join("sub").to_string_lossy().into_owned(),
    ];
    if have_fifo {
        // Twice: each used to block one CPU thread for good.
        hostile.push("fifo.onnx".into());
        hostile.push(fifo.to_string_lossy().into_owned());
    }
    let mut messages = Vec::new();
    for model in &hostile {
        let r = create(model);
        assert_eq!(
            (r.status, r.code().as_str()),
            (422, "inconsistent_parameter"),
            "{model}"
        );
        messages.push(r.message().replace(model.as_str(), "NAME"));
    }
    messages.dedup();
    assert_eq!(messages.len(), 1, "messages tell paths apart: {messages:?}");
    // The CPU pool is free: a HOG map still takes images.
    let map = crate::common::create_hog_map(&c, "after", 8);
    let route = Route::new(4, 1);
    let parts: Vec<Part> = (0..4)
        .map(|i| Part::image(&format!("r{i}.png"), route.reference_png(i)))
        .collect();
    let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &parts);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));

    // Without --model-dir a request may not name a model at all.
    let plain = Server::start();
    let r = plain.client.post_json(
        "/v1/maps",
        &json!({"name": "m", "descriptor": {"kind": "cnn", "model": "/dev/zero", "layer": "pooled"}}),
    );
    assert_eq!(r.status, 422);
    assert!(r.message().contains("--model-dir"), "{}", r.message());
}

#[test]
fn descriptor_length_is_bounded_before_decoding() {
    // 64x32 at cell size 8 gives a short HOG descriptor; a cap below it refuses the image.
    let server = Server::start_with(|a| a.max_descriptor_len = 100);
    let c = server.client;
    let map = crate::common::create_hog_map(&c, "small-cap", 8);
    let route = Route::new(4, 2);
    let parts: Vec<Part> = (0..2)
        .map(|i| Part::image(&format!("r{i}.png"), route.reference_png(i)))
        .collect();
    let r = c.post_multipart(&format!("/v1/maps/{map}/images"), &parts);
    assert_eq!(
        (r.status, r.code().as_str()),
        (422, "descriptor_length"),
        "{}",
        r.message()
    );
    assert!(r.message().contains("limit of 100"), "{}", r.message());
    spec::check("post", "/v1/maps/{id}/images", &r);
    assert_eq!(c.get(&format!("/v1/maps/{map}")).json()["image_count"], 0);
    // The same cap bounds precomputed maps at creation.
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": "v", "descriptor": {"kind": "precomputed", "dim": 101}}),
    );
    // Valid by the schema's bound, over this server's configured cap.
    assert_eq!(
        (r.status, r.code().as_str()),
        (422, "inconsistent_parameter")
    );
    assert!(r.message().contains("descriptor.dim"), "{}", r.message());
    // And HOG maps whose `resize` fixes a descriptor over the cap: such a map could never take
    // an image, so it is refused when created, naming `resize`.
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": "h", "descriptor": {"kind": "hog", "cell_size": 8, "resize": [64, 64]}}),
    );
    assert_eq!(
        (r.status, r.code().as_str()),
        (422, "inconsistent_parameter"),
        "{}",
        r.message()
    );
    assert!(r.message().contains("descriptor.resize"), "{}", r.message());
    assert!(r.message().contains("limit of 100"), "{}", r.message());
    spec::check("post", "/v1/maps", &r);
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": "h", "descriptor": {"kind": "hog", "cell_size": 16, "resize": [32, 16]}}),
    );
    assert_eq!(
        r.status,
        201,
        "a resize under the cap is a map: {}",
        r.message()
    );

    // With the default cap, a small PNG that would expand to a huge descriptor (a 3000x3000
    // blank image on a `cell_size: 2` map: tens of millions of values) is refused from its
    // header, without being decoded.
    let server = Server::start();
    let c = server.client;
    let map = crate::common::create_hog_map(&c, "tiny-cells", 2);
    let blank = crate::common::png(&image::GrayImage::new(3000, 3000));
    assert!(blank.len() < 200_000, "{}", blank.len());
    let r = c.post_multipart(
        &format!("/v1/maps/{map}/images"),
        &[Part::image("big.png", blank)],
    );
    assert_eq!(
        (r.status, r.code().as_str()),
        (422, "descriptor_length"),
        "{}",
        r.message()
    );
}
