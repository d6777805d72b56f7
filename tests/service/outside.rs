//! Regression tests of what the second outside reliability test found (issue 42): metric labels
//! a keyless client could grow, a batch of decompression bombs under a memory limit, slow
//! bodies holding the localize queue and the probes, CSRF and DNS rebinding on keyless
//! loopback serving, half-open connections starving probes, unbounded request ids, and a
//! localization without predictions that did not say why.
//!
//! Every server listens on 127.0.0.1; every load is bounded in count and time.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde_json::json;
use sha2::{Digest, Sha256};

use crate::common::{create_hog_map, create_vector_map, engine_database, Process, Route, Server};
use crate::http::{multipart_body, Client, Part, BOUNDARY};
use crate::spec;

const ADMIN: &str = "adm-42c1f0e9d8b7a6";
const READER: &str = "rd-42e5d4c3b2a190";

/// A key file with an admin and a reader key.
fn write_keys(path: &Path) {
    let entry = |name: &str, role: &str, key: &str| {
        let sha: String = Sha256::digest(key.as_bytes())
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        json!({"name": name, "role": role, "sha256": sha})
    };
    let keys = json!({"keys": [entry("ops", "admin", ADMIN), entry("wall", "reader", READER)]});
    std::fs::write(path, keys.to_string()).unwrap();
}

fn bearer(key: &str) -> String {
    format!("Bearer {key}")
}

/// `n` route frames as multipart image parts (references, or queries of the other season).
fn frames(route: &Route, range: std::ops::Range<u32>, query: bool) -> Vec<Part> {
    range
        .map(|i| {
            let png = if query {
                route.query_png(i)
            } else {
                route.reference_png(i)
            };
            Part::image(&format!("f{i}.png"), png)
        })
        .collect()
}

/// A HOG map of `n` frames of `route`.
fn hog_map(client: &Client, route: &Route, n: u32) -> String {
    let map = create_hog_map(client, "route", 8);
    let r = client.post_multipart(
        &format!("/v1/maps/{map}/images"),
        &frames(route, 0..n, false),
    );
    assert_eq!(r.status, 200, "{}", r.message());
    map
}

// ---- 1: metric labels --------------------------------------------------------------------------

#[test]
fn distinct_long_methods_never_become_metric_labels() {
    let dir = tempfile::tempdir().unwrap();
    let keys = dir.path().join("keys.json");
    write_keys(&keys);
    let server = Server::start_with(|a| a.api_keys = Some(keys.clone()));
    let c = server.client;
    let reader = bearer(READER);
    let metrics =
        |c: &Client| c.request_with("GET", "/metrics", &[("Authorization", &reader)], None, b"");
    let before = metrics(&c).body.len();
    // 300 requests without a key, each with its own 1,000-character method (answered before
    // any key is checked for, or with 401).
    for n in 0..300 {
        let method = format!("M{n:07}{}", "X".repeat(992));
        let path = if n % 2 == 0 { "/healthz" } else { "/v1/maps" };
        let r = c.request(&method, path, None, b"");
        assert!(r.status >= 400, "{n}: {}", r.status);
    }
    let r = metrics(&c);
    assert_eq!(r.status, 200);
    let text = String::from_utf8(r.body).unwrap();
    assert!(
        !text.contains("XXXXXXXX"),
        "a client's method became a label"
    );
    assert!(
        text.contains("method=\"other\""),
        "extension methods are counted under `other`"
    );
    // A few more series (`other` per route and status), not one per request.
    assert!(
        text.len() < before + 8_000,
        "/metrics grew from {before} to {} bytes",
        text.len()
    );
}

// ---- 2: decoded pixels under a memory limit ----------------------------------------------------

/// An all-zero 8-bit grey PNG of `w` x `h`: about 16 KB on the wire for 4000 x 4000, 16 MB
/// decoded.
fn zero_png(w: u32, h: u32) -> Vec<u8> {
    let mut out = Vec::new();
    let encoder = image::codecs::png::PngEncoder::new_with_quality(
        &mut out,
        image::codecs::png::CompressionType::Best,
        image::codecs::png::FilterType::NoFilter,
    );
    image::ImageEncoder::write_image(
        encoder,
        &vec![0u8; (w * h) as usize],
        w,
        h,
        image::ExtendedColorType::L8,
    )
    .unwrap();
    out
}

/// A memory limit for one child process: a cgroup (v2 if the unified hierarchy has the memory
/// controller, else v1) when this process may make one (root), else the child's address space
/// (`ulimit -v`, RLIMIT_AS, which any user may lower; `SEASONLOC_TEST_RLIMIT_AS=1` picks it
/// always).
enum MemoryLimit {
    Cgroup { dir: PathBuf, v2: bool },
    AddressSpace,
}

/// The limit under a cgroup: the 128 images of a batch decode to 2 GB at once.
const CGROUP_LIMIT: u64 = 768 << 20;
/// The limit of the address space, which also counts what is reserved and never touched (the
/// allocator's per-thread arenas, thread stacks): an idle server reserves about 800 MB.
const ADDRESS_SPACE_LIMIT: u64 = 1536 << 20;

impl MemoryLimit {
    fn new(tag: &str) -> MemoryLimit {
        if std::env::var_os("SEASONLOC_TEST_RLIMIT_AS").is_some() {
            return MemoryLimit::AddressSpace;
        }
        let bytes = CGROUP_LIMIT;
        let name = format!("seasonloc-test-{}-{tag}", std::process::id());
        let v2 = Path::new("/sys/fs/cgroup");
        let controllers =
            std::fs::read_to_string(v2.join("cgroup.controllers")).unwrap_or_default();
        if controllers.split_whitespace().any(|c| c == "memory") {
            let _ = std::fs::write(v2.join("cgroup.subtree_control"), "+memory");
            let dir = v2.join(&name);
            if std::fs::create_dir(&dir).is_ok() {
                if std::fs::write(dir.join("memory.max"), bytes.to_string()).is_ok() {
                    let _ = std::fs::write(dir.join("memory.swap.max"), "0");
                    return MemoryLimit::Cgroup { dir, v2: true };
                }
                let _ = std::fs::remove_dir(&dir);
            }
        }
        let v1 = Path::new("/sys/fs/cgroup/memory");
        if v1.join("cgroup.procs").exists() {
            let dir = v1.join(&name);
            if std::fs::create_dir(&dir).is_ok() {
                if std::fs::write(dir.join("memory.limit_in_bytes"), bytes.to_string()).is_ok() {
                    let _ =
                        std::fs::write(dir.join("memory.memsw.limit_in_bytes"), bytes.to_string());
                    return MemoryLimit::Cgroup { dir, v2: false };
                }
                let _ = std::fs::remove_dir(&dir);
            }
        }
        MemoryLimit::AddressSpace
    }

    /// The limit in bytes.
    fn bytes(&self) -> u64 {
        match self {
            MemoryLimit::Cgroup { .. } => CGROUP_LIMIT,
            MemoryLimit::AddressSpace => ADDRESS_SPACE_LIMIT,
        }
    }

    /// `sh -c` arguments that put the child under the limit, then `exec` it.
    fn shell(&self) -> Vec<String> {
        let bytes = self.bytes();
        match self {
            MemoryLimit::Cgroup { dir, .. } => vec![
                "-c".into(),
                r#"echo $$ > "$0" && exec "$@""#.into(),
                dir.join("cgroup.procs").display().to_string(),
            ],
            MemoryLimit::AddressSpace => vec![
                "-c".into(),
                r#"ulimit -v "$0" && exec "$@""#.into(),
                (bytes / 1024).to_string(),
            ],
        }
    }

    fn describe(&self) -> &'static str {
        match self {
            MemoryLimit::Cgroup { v2: true, .. } => "cgroup v2 memory.max",
            MemoryLimit::Cgroup { v2: false, .. } => "cgroup v1 memory.limit_in_bytes",
            MemoryLimit::AddressSpace => "RLIMIT_AS (ulimit -v)",
        }
    }

    /// The cgroup's peak memory, if it has one.
    fn peak(&self) -> Option<u64> {
        let MemoryLimit::Cgroup { dir, v2 } = self else {
            return None;
        };
        let file = if *v2 {
            "memory.peak"
        } else {
            "memory.max_usage_in_bytes"
        };
        std::fs::read_to_string(dir.join(file))
            .ok()?
            .trim()
            .parse()
            .ok()
    }
}

impl Drop for MemoryLimit {
    fn drop(&mut self) {
        if let MemoryLimit::Cgroup { dir, .. } = self {
            for _ in 0..50 {
                if std::fs::remove_dir(&*dir).is_ok() || !dir.exists() {
                    return;
                }
                std::thread::sleep(Duration::from_millis(100));
            }
        }
    }
}

/// `VmHWM` (peak resident memory) of a process, in bytes.
fn peak_rss(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let kb: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))?
        .split_whitespace()
        .next()?
        .parse()
        .ok()?;
    Some(kb * 1024)
}

/// The serve arguments of a child process on this test binary's engine.
fn engine_args(data: &Path) -> Vec<String> {
    let mut args = vec![
        "--addr".to_string(),
        "127.0.0.1:0".to_string(),
        "--data-dir".to_string(),
        data.display().to_string(),
    ];
    if let Some(url) = engine_database() {
        args.extend(["--database-url".to_string(), url]);
    }
    args
}

#[test]
fn a_batch_of_decompression_bombs_is_decoded_within_a_memory_limit() {
    let dir = tempfile::tempdir().unwrap();
    let limit = MemoryLimit::new("bombs");
    let mut args = engine_args(&dir.path().join("data"));
    args.extend(["--worker-threads", "2", "--request-timeout-secs", "100"].map(String::from));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let shell = limit.shell();
    let shell: Vec<&str> = shell.iter().map(String::as_str).collect();
    let log = dir.path().join("serve.log");
    let mut server = Process::start_under(&shell, &args, &[], &log);
    let c = server.client;
    let route = Route::new(20, 42);
    let map = hog_map(&c, &route, 20);
    let trip = c.post_json(&format!("/v1/maps/{map}/trips"), &json!({}));
    assert_eq!(trip.status, 201, "{}", trip.message());
    let trip = trip.json()["id"].as_str().unwrap().to_string();
    // 16 MB decoded each, 2 GB for the 128 of a batch at once.
    let bomb = zero_png(4000, 4000);
    let started = Instant::now();
    for (route, path, n) in [
        ("trip frames", format!("/v1/trips/{trip}/frames"), 128),
        ("localize", format!("/v1/maps/{map}/localize"), 128),
        ("images", format!("/v1/maps/{map}/images"), 64),
    ] {
        let parts: Vec<Part> = (0..n)
            .map(|i| Part::image(&format!("zero{i}.png"), bomb.clone()))
            .collect();
        let sent = Instant::now();
        let r = c.try_request(
            "POST",
            &path,
            Some(&format!("multipart/form-data; boundary={BOUNDARY}")),
            &multipart_body(&parts),
        );
        let alive = server.alive();
        let peak = limit.peak().or_else(|| peak_rss(server.child.id()));
        eprintln!(
            "{route} x{n} ({} KB): {:?} after {:.1} s; peak {} MiB under {} of {} MiB",
            n * bomb.len() / 1024,
            r.as_ref().map(|r| r.status),
            sent.elapsed().as_secs_f64(),
            peak.map_or(-1, |p| (p >> 20) as i64),
            limit.describe(),
            limit.bytes() >> 20
        );
        let log_text = std::fs::read_to_string(&log).unwrap_or_default();
        assert!(
            alive,
            "{n} zero 4000x4000 PNGs as {route} killed the server under {}: {}",
            limit.describe(),
            log_text.lines().last().unwrap_or("")
        );
        let r = r.unwrap_or_else(|e| panic!("{route}: {e}"));
        assert!(
            r.status == 200 || (400..500).contains(&r.status),
            "{route}: {} {}",
            r.status,
            r.message()
        );
    }
    assert!(started.elapsed() < Duration::from_secs(240));
}

#[test]
fn a_co_occurrence_batch_over_the_pixel_budget_is_refused_before_decoding() {
    // A co-occurrence map's first batch is held decoded whole: 20 frames of 64 x 32 are
    // 40,960 pixels, over a budget of 40,000.
    let server = Server::start_with(|a| a.max_batch_pixels = 40_000);
    let c = server.client;
    let r = c.post_json(
        "/v1/maps",
        &json!({"name": "cooc", "descriptor": {"kind": "cooc", "vocabulary_branching": 8}}),
    );
    assert_eq!(r.status, 201, "{}", r.message());
    let map = r.json()["id"].as_str().unwrap().to_string();
    let route = Route::new(20, 5);
    let path = format!("/v1/maps/{map}/images");
    let r = c.post_multipart(&path, &frames(&route, 0..20, false));
    assert_eq!(
        (r.status, r.code().as_str()),
        (400, "batch_too_large"),
        "{}",
        r.message()
    );
    assert!(r.message().contains("40960 pixels"), "{}", r.message());
    spec::check("post", "/v1/maps/{id}/images", &r);
    assert_eq!(c.get(&format!("/v1/maps/{map}")).json()["image_count"], 0);
    // Within the budget the same map is built.
    let r = c.post_multipart(&path, &frames(&route, 0..19, false));
    assert_eq!(r.status, 200, "{}", r.message());
}

// ---- 3: slow bodies ----------------------------------------------------------------------------

/// A request whose header and the start of a multipart body are sent at once; the rest never
/// comes (until `drip` is called).
struct SlowBody {
    stream: TcpStream,
}

impl SlowBody {
    fn open(addr: SocketAddr, path: &str) -> SlowBody {
        let mut stream = TcpStream::connect(addr).unwrap();
        let head = format!(
            "POST {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: multipart/form-data; \
             boundary={BOUNDARY}\r\nContent-Length: 1000000\r\n\r\n--{BOUNDARY}\r\n\
             Content-Disposition: form-data; name=\"image\"; filename=\"slow.png\"\r\n\
             Content-Type: image/png\r\n\r\n"
        );
        stream.write_all(head.as_bytes()).unwrap();
        SlowBody { stream }
    }

    /// Sends one more byte of the body (false once the server has closed the connection).
    fn drip(&mut self) -> bool {
        self.stream.write_all(b"\0").is_ok()
    }

    /// The status the server answered with, waiting at most `bound`.
    fn status(&mut self, bound: Duration) -> Option<u16> {
        self.stream.set_read_timeout(Some(bound)).unwrap();
        let mut buf = [0u8; 512];
        let n = self.stream.read(&mut buf).ok()?;
        let text = String::from_utf8_lossy(&buf[..n]);
        text.split(' ').nth(1)?.parse().ok()
    }
}

#[test]
fn a_body_that_keeps_trickling_gets_408_at_its_deadline() {
    let server = Server::start_with(|a| {
        a.body_deadline_secs = 2;
        a.body_read_timeout_secs = 20;
    });
    let c = server.client;
    let map = create_hog_map(&c, "m", 8);
    let mut slow = SlowBody::open(c.addr, &format!("/v1/maps/{map}/images"));
    let started = Instant::now();
    // One byte every 200 ms: never a stall, but never a whole body either.
    let status = loop {
        if !slow.drip() {
            break slow.status(Duration::from_secs(5));
        }
        if let Some(s) = slow.status(Duration::from_millis(200)) {
            break Some(s);
        }
        assert!(
            started.elapsed() < Duration::from_secs(15),
            "a trickling body was still being read after {:?}",
            started.elapsed()
        );
    };
    assert_eq!(status, Some(408), "after {:?}", started.elapsed());
    assert!(started.elapsed() >= Duration::from_secs(2));
    assert_eq!(c.get(&format!("/v1/maps/{map}")).json()["image_count"], 0);
}

#[test]
fn slow_localize_bodies_hold_no_place_in_the_queue() {
    let server = Server::start_with(|a| {
        a.localize_queue = 2;
        a.body_deadline_secs = 60;
    });
    let c = server.client;
    let map = create_vector_map(&c, "v", 2);
    let r = c.post_json(
        &format!("/v1/maps/{map}/descriptors"),
        &json!({"descriptors": [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]}),
    );
    assert_eq!(r.status, 200, "{}", r.message());
    // Four localize bodies that never arrive (twice the queue), and one to a map that does not
    // exist.
    let mut slow: Vec<SlowBody> = (0..4)
        .map(|_| SlowBody::open(c.addr, &format!("/v1/maps/{map}/localize")))
        .collect();
    let mut unknown = SlowBody::open(c.addr, "/v1/maps/00000000000000ab/localize");
    assert_eq!(unknown.status(Duration::from_secs(10)), Some(404));
    std::thread::sleep(Duration::from_millis(300));
    for s in &mut slow {
        assert!(s.drip());
    }
    let started = Instant::now();
    let r = c.post_json(
        &format!("/v1/maps/{map}/localize"),
        &json!({"descriptors": [[1.0, 0.1], [0.1, 1.0]]}),
    );
    assert_eq!(r.status, 200, "{} {}", r.code(), r.message());
    assert!(started.elapsed() < Duration::from_secs(5));
}

/// Status of `GET path` within `bound` (None when no answer came in time).
fn probe(addr: SocketAddr, path: &str, bound: Duration) -> Option<u16> {
    let mut s = TcpStream::connect_timeout(&addr, bound).ok()?;
    s.set_read_timeout(Some(bound)).ok()?;
    s.write_all(
        format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").as_bytes(),
    )
    .ok()?;
    let mut buf = [0u8; 256];
    let n = s.read(&mut buf).ok()?;
    String::from_utf8_lossy(&buf[..n])
        .split(' ')
        .nth(1)?
        .parse()
        .ok()
}

#[test]
fn probes_answer_while_slow_uploads_hold_every_request_slot() {
    let server = Server::start_with(|a| {
        a.max_concurrent_requests = 4;
        a.body_deadline_secs = 60;
    });
    let c = server.client;
    let map = create_hog_map(&c, "m", 8);
    let slow: Vec<SlowBody> = (0..6)
        .map(|_| SlowBody::open(c.addr, &format!("/v1/maps/{map}/images")))
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    // The limit is taken: an API request is shed ...
    let r = c.get("/v1/maps");
    assert_eq!((r.status, r.code().as_str()), (503, "overloaded"));
    spec::check("get", "/v1/maps", &r);
    // ... and the probes and the dashboard's front page are not.
    for path in ["/healthz", "/readyz", "/"] {
        let started = Instant::now();
        assert_eq!(
            probe(c.addr, path, Duration::from_secs(2)),
            Some(200),
            "{path}"
        );
        assert!(started.elapsed() < Duration::from_secs(2), "{path}");
    }
    drop(slow);
}

// ---- 9: keyless loopback: DNS rebinding and CSRF -----------------------------------------------

#[test]
fn keyless_loopback_answers_only_loopback_names_and_addresses() {
    let server = Server::start();
    let c = server.client;
    let port = c.addr.port();
    for host in [
        format!("127.0.0.1:{port}"),
        format!("localhost:{port}"),
        "[::1]".into(),
    ] {
        let r = c.request_with("GET", "/v1/maps", &[("Host", &host)], None, b"");
        assert_eq!(r.status, 200, "Host {host}: {}", r.message());
    }
    for host in [
        "attacker-rebind.example".to_string(),
        format!("attacker-rebind.example:{port}"),
    ] {
        let r = c.request_with("GET", "/v1/maps", &[("Host", &host)], None, b"");
        assert_eq!(
            (r.status, r.code().as_str()),
            (421, "misdirected_request"),
            "{host}"
        );
        spec::check("get", "/v1/maps", &r);
        // The probes answer under any name.
        let r = c.request_with("GET", "/healthz", &[("Host", &host)], None, b"");
        assert_eq!(r.status, 200);
    }
}

#[test]
fn keyless_loopback_refuses_cross_site_writes() {
    let server = Server::start();
    let c = server.client;
    let route = Route::new(12, 7);
    let map = hog_map(&c, &route, 10);
    let trip = c.post_json(&format!("/v1/maps/{map}/trips"), &json!({}));
    let trip = trip.json()["id"].as_str().unwrap().to_string();
    let close = format!("/v1/trips/{trip}/close");
    let evil = [
        ("Origin", "http://evil.example"),
        ("Referer", "http://evil.example/page"),
        ("Sec-Fetch-Site", "cross-site"),
    ];
    // What a hostile page can send without a preflight: a text/plain or form POST ...
    for ct in [
        "text/plain;charset=UTF-8",
        "application/x-www-form-urlencoded",
    ] {
        let r = c.request_with("POST", &close, &evil, Some(ct), b"a=1");
        assert_eq!(
            (r.status, r.code().as_str()),
            (403, "cross_site_request"),
            "{ct}"
        );
        spec::check("post", "/v1/trips/{id}/close", &r);
        // ... refused also without the cross-site headers (old browsers send none).
        let r = c.request_with("POST", &close, &[], Some(ct), b"a=1");
        assert_eq!(
            (r.status, r.code().as_str()),
            (415, "unsupported_media_type"),
            "{ct}"
        );
        spec::check("post", "/v1/trips/{id}/close", &r);
    }
    assert!(c.get(&format!("/v1/trips/{trip}")).json()["closed_at_ms"].is_null());
    // ... and a multipart upload from its origin.
    let body = multipart_body(&frames(&route, 10..12, false));
    let ct = format!("multipart/form-data; boundary={BOUNDARY}");
    let images = format!("/v1/maps/{map}/images");
    let r = c.request_with("POST", &images, &evil[..1], Some(&ct), &body);
    assert_eq!((r.status, r.code().as_str()), (403, "cross_site_request"));
    spec::check("post", "/v1/maps/{id}/images", &r);
    let r = c.request_with(
        "POST",
        &images,
        &[("Sec-Fetch-Site", "same-site")],
        Some(&ct),
        &body,
    );
    assert_eq!(r.status, 403);
    assert_eq!(c.get(&format!("/v1/maps/{map}")).json()["image_count"], 10);
    // Programs (no Origin), this server's own pages and a custom header are served.
    let own = format!("http://{}", c.addr);
    let r = c.request_with("POST", &images, &[("Origin", &own)], Some(&ct), &body);
    assert_eq!(r.status, 200, "{}", r.message());
    let r = c.request_with(
        "POST",
        &close,
        &[evil[0], ("X-Requested-With", "fetch")],
        Some("text/plain"),
        b"",
    );
    assert_eq!(r.status, 200, "{}", r.message());
    assert!(!c.get(&format!("/v1/trips/{trip}")).json()["closed_at_ms"].is_null());
}

// ---- 10: connections and request ids -----------------------------------------------------------

/// The soft limit on this process's open files.
fn own_descriptor_limit() -> usize {
    std::fs::read_to_string("/proc/self/limits")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("Max open files"))
                .and_then(|l| l.split_whitespace().nth(3)?.parse().ok())
        })
        .unwrap_or(1024)
}

/// Keeps up to `n` half-open connections (half a request header each) to `addr` until
/// `stop`: each one the server closes is opened again.
fn half_open_clients(
    addr: SocketAddr,
    n: usize,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> std::thread::JoinHandle<usize> {
    std::thread::spawn(move || {
        let mut held: Vec<TcpStream> = Vec::new();
        let mut opened = 0;
        let half = format!("GET /healthz HTTP/1.1\r\nHost: {addr}\r\n");
        while !stop.load(std::sync::atomic::Ordering::Relaxed) {
            while held.len() < n {
                let Ok(mut s) = TcpStream::connect_timeout(&addr, Duration::from_millis(500))
                else {
                    break;
                };
                let _ = s.write_all(half.as_bytes());
                let _ = s.set_nonblocking(true);
                held.push(s);
                opened += 1;
            }
            let mut buf = [0u8; 64];
            held.retain_mut(|s| match s.read(&mut buf) {
                Ok(0) => false,
                Ok(_) => true,
                Err(e) => e.kind() == std::io::ErrorKind::WouldBlock,
            });
            std::thread::sleep(Duration::from_millis(20));
        }
        opened
    })
}

#[test]
fn half_open_connections_past_the_descriptor_limit_do_not_starve_probes() {
    const NOFILE: usize = 256;
    const HELD: usize = 400;
    if own_descriptor_limit() < HELD + 200 {
        eprintln!(
            "SKIPPED: this test process may open {} files; it needs {} for {HELD} connections",
            own_descriptor_limit(),
            HELD + 200
        );
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut args = engine_args(&dir.path().join("data"));
    // Half-open connections are never let go by the header timeout during the test.
    args.extend(["--header-read-timeout-secs", "60"].map(String::from));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let log = dir.path().join("serve.log");
    let limit = NOFILE.to_string();
    let mut server = Process::start_under(
        &["-c", r#"ulimit -n "$0" && exec "$@""#, &limit],
        &args,
        &[],
        &log,
    );
    let addr = server.client.addr;
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let attacker = half_open_clients(addr, HELD, std::sync::Arc::clone(&stop));
    std::thread::sleep(Duration::from_secs(2));
    let mut answered = Vec::new();
    for _ in 0..6 {
        let started = Instant::now();
        let status = probe(addr, "/healthz", Duration::from_secs(2));
        answered.push((status, started.elapsed()));
        std::thread::sleep(Duration::from_millis(300));
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let opened = attacker.join().unwrap();
    let failed: Vec<_> = answered
        .iter()
        .filter(|(s, t)| *s != Some(200) || *t > Duration::from_secs(2))
        .collect();
    assert!(
        failed.is_empty(),
        "{} of {} probes failed under {opened} half-open connections ({NOFILE} descriptors): \
         {answered:?}",
        failed.len(),
        answered.len()
    );
    assert!(opened >= HELD, "only {opened} connections were opened");
    // A 16,000-character request id is neither echoed nor logged whole; a short one is kept.
    let c = server.client;
    let long = "r".repeat(16_000);
    let r = c.request_with("GET", "/healthz", &[("x-request-id", &long)], None, b"");
    assert_eq!(r.status, 200);
    let echoed = r.header("x-request-id").unwrap_or("");
    assert!(
        !echoed.is_empty() && echoed.len() <= 128,
        "{} characters",
        echoed.len()
    );
    let r = c.request_with(
        "GET",
        "/healthz",
        &[("x-request-id", "trace-42")],
        None,
        b"",
    );
    assert_eq!(r.header("x-request-id"), Some("trace-42"));
    std::thread::sleep(Duration::from_millis(200));
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(
        !text.contains(&"r".repeat(129)),
        "the long request id was logged"
    );
    assert!(server.alive());
}

// ---- S2: a localization without predictions says why --------------------------------------------

#[test]
fn a_localization_without_informative_predictions_says_why() {
    let server = Server::start();
    let c = server.client;
    let route = Route::new(60, 3);
    let map = hog_map(&c, &route, 60);
    let localize = format!("/v1/maps/{map}/localize");
    // One image: with the column normalisation every reference scores alike.
    let r = c.post_multipart(&localize, &frames(&route, 20..21, true));
    assert_eq!(r.status, 200, "{}", r.message());
    spec::check("post", "/v1/maps/{id}/localize", &r);
    let one = r.json();
    assert_eq!(one["reason"], "too_few_queries", "{one}");
    // Stored, it says the same.
    let id = one["id"].as_str().unwrap();
    let stored = c.get(&format!("/v1/localizations/{id}"));
    assert_eq!(stored.json()["reason"], "too_few_queries");
    // A sequence localizes, and needs no reason.
    let r = c.post_multipart(&localize, &frames(&route, 20..30, true));
    assert_eq!(r.status, 200, "{}", r.message());
    let seq = r.json();
    assert!(!seq["predictions"].as_array().unwrap().is_empty(), "{seq}");
    assert!(seq.get("reason").is_none(), "{seq}");
    // Hiding a row cheaper than any match: every row hidden, no prediction, and that says why.
    let mut parts = frames(&route, 20..30, true);
    parts.push(Part::json("params", &json!({"hidden_cost": 1e-6})));
    let r = c.post_multipart(&localize, &parts);
    assert_eq!(r.status, 200, "{}", r.message());
    spec::check("post", "/v1/maps/{id}/localize", &r);
    let hidden = r.json();
    assert_eq!(hidden["predictions"], json!([]), "{hidden}");
    assert_eq!(hidden["reason"], "every_row_hidden", "{hidden}");
}
