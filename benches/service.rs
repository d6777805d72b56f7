//! Load benchmark of the HTTP path: images per second ingested and localized through the
//! running service with 8 concurrent clients, against the same requests made in process to the
//! use-case layer ([`seasonloc_app::App`] on its own sled store, 8 concurrent tasks, same CPU
//! pool size), and against the algorithms alone (decode + HOG + localize, batch after batch).
//!
//! Run: `cargo bench --bench service` (`SEASONLOC_BENCH_ROUNDS` scales the work). Uses the
//! Nordland thumbnails from `../shared/data` when present, generated 64x32 frames otherwise.
//! Prints a markdown table. The HTTP clients keep their connection open across requests, as a fleet's
//! client does. The HTTP overhead is `use-case rate / HTTP rate - 1`: both do
//! everything a request asks for (reference thumbnails, the store's flushed write, storing the
//! localization result), so the difference is HTTP itself (connections, multipart parsing,
//! routing, admission, JSON). The algorithms-alone column shows what the use cases add.
//! Besides the rates it prints the server's CPU time per localized image in both paths (is
//! HTTP's extra time CPU, or waiting?) and the latency of one localize at a time for batches of
//! 1 to 50 images (what HTTP adds per request and per uploaded image).

mod fixture;

#[path = "../tests/service/http.rs"]
#[allow(dead_code)]
mod http;

use std::io::Cursor;
use std::path::Path;
use std::time::Instant;

use std::sync::Arc;

use http::{Client, Part};
use seasonloc_app::{App, DescriptorSpec, ImageInput, LocalizeInput, NewMapSpec, Queries, Upload};
use seasonloc_core::features::hog::{HogOptions, HogSpec};
use seasonloc_core::features::{decode_image, extract_batch};
use seasonloc_core::localize::{localize, LocalizeOptions};
use seasonloc_core::solver::{HiddenCost, SolverParams};
use seasonloc_server::config::{ServeArgs, Settings};

const CLIENTS: usize = 8;
const BATCH: usize = 50;
const CELL: u32 = 8;
/// Requests of the one-at-a-time latency measurement, per batch size.
const LATENCY_REQUESTS: usize = 64;
/// Batch sizes of the one-at-a-time latency measurement: what HTTP adds per request and per
/// image (the body grows with the batch).
const LATENCY_SIZES: [usize; 4] = [1, 10, 25, BATCH];

/// The median of `times` in milliseconds.
fn median_ms(times: impl Iterator<Item = std::time::Duration>) -> f64 {
    let mut ms: Vec<f64> = times.map(|t| t.as_secs_f64() * 1e3).collect();
    ms.sort_by(f64::total_cmp);
    ms[ms.len() / 2]
}

fn images() -> (Vec<Vec<u8>>, Vec<Vec<u8>>, &'static str) {
    let dir = fixture::data_dir("nordland_64x32");
    let read = |season: &str| -> Option<Vec<Vec<u8>>> {
        let mut files: Vec<_> = std::fs::read_dir(dir.join(season))
            .ok()?
            .map(|e| e.map(|e| e.path()))
            .collect::<Result<_, _>>()
            .ok()?;
        files.sort();
        files
            .iter()
            .take(800)
            .map(|p| std::fs::read(p).ok())
            .collect()
    };
    if let (Some(s), Some(w)) = (read("summer"), read("winter")) {
        return (s, w, "Nordland 64x32 PNG");
    }
    eprintln!(
        "Nordland data not found at {}; using generated frames",
        dir.display()
    );
    let frame = |i: usize, dark: bool| {
        let img = image::GrayImage::from_fn(64, 32, |x, y| {
            let v = ((x as usize * 7 + i * 5) % 97 + (y as usize * 3) % 41) as f32;
            image::Luma([if dark { v * 0.6 + 20.0 } else { v * 2.0 } as u8])
        });
        let mut out = Vec::new();
        img.write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png)
            .expect("encode");
        out
    };
    (
        (0..800).map(|i| frame(i, false)).collect(),
        (0..800).map(|i| frame(i, true)).collect(),
        "generated 64x32 PNG",
    )
}

fn options() -> LocalizeOptions {
    LocalizeOptions {
        solver: SolverParams {
            hidden_cost: HiddenCost::Fixed(1.3),
            ..SolverParams::default()
        },
        normalization: seasonloc_core::similarity::Normalization::default(),
        ..Default::default()
    }
}

fn start_server(
    threads: usize,
) -> (
    Client,
    tokio::sync::oneshot::Sender<()>,
    std::thread::JoinHandle<()>,
    tempfile::TempDir,
) {
    let dir = tempfile::tempdir().expect("tempdir");
    let settings = settings(dir.path(), threads);
    let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    listener.set_nonblocking(true).expect("nonblocking");
    let addr = listener.local_addr().expect("addr");
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let handle = std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .expect("runtime");
        rt.block_on(async move {
            let listener = tokio::net::TcpListener::from_std(listener).expect("listener");
            seasonloc_server::service::serve(settings, listener, async move {
                let _ = rx.await;
            })
            .await
            .expect("serve");
        });
    });
    (Client::new(addr), tx, handle, dir)
}

/// One HTTP/1.1 connection kept open across requests, as a fleet's client keeps it (the
/// test client opens one per request): a request is written whole, its answer read by its
/// `Content-Length`.
struct KeepAlive {
    stream: std::net::TcpStream,
    host: String,
}

impl KeepAlive {
    fn connect(addr: std::net::SocketAddr) -> Self {
        let stream = std::net::TcpStream::connect(addr).expect("connect");
        stream.set_nodelay(true).expect("nodelay");
        KeepAlive {
            stream,
            host: addr.to_string(),
        }
    }

    /// POSTs `body` to `path`; the status and the body of the answer.
    fn post(&mut self, path: &str, content_type: &str, body: &[u8]) -> (u16, Vec<u8>) {
        use std::io::{BufRead, Read, Write};
        let head = format!(
            "POST {path} HTTP/1.1\r\nHost: {}\r\nContent-Type: {content_type}\r\nContent-Length: {}\r\n\r\n",
            self.host,
            body.len()
        );
        self.stream.write_all(head.as_bytes()).expect("write");
        self.stream.write_all(body).expect("write");
        let mut reader = std::io::BufReader::new(&self.stream);
        let mut line = String::new();
        reader.read_line(&mut line).expect("status line");
        let status: u16 = line
            .split(' ')
            .nth(1)
            .and_then(|s| s.parse().ok())
            .expect("a status");
        let mut len = 0;
        loop {
            line.clear();
            reader.read_line(&mut line).expect("header");
            let l = line.trim_end();
            if l.is_empty() {
                break;
            }
            if let Some((k, v)) = l.split_once(':') {
                if k.eq_ignore_ascii_case("content-length") {
                    len = v.trim().parse().expect("a length");
                }
            }
        }
        let mut answer = vec![0; len];
        reader.read_exact(&mut answer).expect("body");
        assert!(reader.buffer().is_empty(), "nothing after the answer");
        (status, answer)
    }
}

/// CPU seconds the calling thread has used (user + system, Linux `/proc`; 0 elsewhere).
fn thread_cpu_secs() -> f64 {
    cpu_secs("/proc/thread-self/stat")
}

/// CPU seconds the whole process has used (every thread; user + system).
fn process_cpu_secs() -> f64 {
    cpu_secs("/proc/self/stat")
}

/// utime + stime of a `/proc` `stat` file, in seconds; 0 when it cannot be read.
fn cpu_secs(path: &str) -> f64 {
    let Ok(stat) = std::fs::read_to_string(path) else {
        return 0.0;
    };
    // Fields after the command name (which ends with the last ')'): utime and stime are the
    // 12th and 13th, in clock ticks of 1/100 s.
    let fields: Vec<&str> = stat
        .rsplit_once(')')
        .map_or("", |(_, rest)| rest)
        .split_whitespace()
        .collect();
    let ticks = |i: usize| {
        fields
            .get(i)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    (ticks(11) + ticks(12)) / 100.0
}

/// The service's settings with its data in `dir` and `threads` CPU threads.
fn settings(dir: &Path, threads: usize) -> Settings {
    ServeArgs {
        data_dir: dir.to_path_buf(),
        worker_threads: threads,
        localize_queue: 64,
        ..ServeArgs::default()
    }
    .validate()
    .expect("settings")
}

/// The use-case layer as the service builds it from the same settings, on a sled store in
/// `dir`.
fn use_cases(dir: &Path, threads: usize) -> App {
    let s = settings(dir, threads);
    let store = seasonloc_store::SledStore::open(&s.data_dir).expect("store");
    App::new(Arc::new(store), seasonloc_server::service::app_config(&s)).expect("use cases")
}

/// The parts of a batch as the API hands them to the use cases.
fn inputs(images: &[Vec<u8>]) -> Vec<ImageInput> {
    images
        .iter()
        .enumerate()
        .map(|(i, b)| ImageInput {
            name: format!("image[{i}] (\"{i}.png\")"),
            bytes: bytes::Bytes::from(b.clone()),
        })
        .collect()
}

/// Runs `jobs` on `clients` concurrent tasks of a 2-worker runtime (as the server's), each
/// task taking every `clients`-th job in turn; returns the seconds it took.
fn concurrently<F, Fut>(clients: usize, jobs: usize, job: F) -> f64
where
    F: Fn(usize, usize) -> Fut + Send + Sync + 'static,
    Fut: std::future::Future<Output = ()> + Send + 'static,
{
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let job = Arc::new(job);
    rt.block_on(async move {
        let t = Instant::now();
        let tasks: Vec<_> = (0..clients)
            .map(|k| {
                let job = Arc::clone(&job);
                tokio::spawn(async move {
                    for j in (k..jobs).step_by(clients) {
                        job(k, j).await;
                    }
                })
            })
            .collect();
        for t in tasks {
            t.await.expect("task");
        }
        t.elapsed().as_secs_f64()
    })
}

fn parts(images: &[Vec<u8>]) -> Vec<Part> {
    images
        .iter()
        .enumerate()
        .map(|(i, b)| Part::image(&format!("{i}.png"), b.clone()))
        .collect()
}

/// The workload: reference and query images in batches, `rounds` passes, `threads` CPUs.
struct Workload {
    refs: Vec<Vec<u8>>,
    queries: Vec<Vec<u8>>,
    rounds: usize,
    threads: usize,
}

impl Workload {
    fn ingest_batches(&self) -> Vec<&[Vec<u8>]> {
        self.refs.chunks(BATCH).collect()
    }

    fn query_batches(&self) -> Vec<&[Vec<u8>]> {
        self.queries.chunks(BATCH).collect()
    }

    /// Images per second when `rounds` passes over `images` took `secs`.
    fn rate(&self, images: &[Vec<u8>], secs: f64) -> f64 {
        (self.rounds * images.len()) as f64 / secs
    }
}

/// Images per second of one column.
struct Rates {
    ingest: f64,
    localize: f64,
}

/// The algorithms alone, batch after batch on a rayon pool: ingest without and with the
/// store's flushed append, and localize.
fn algorithms_alone(w: &Workload) -> (f64, Rates) {
    let spec = HogSpec::new(HogOptions {
        cell_size: CELL,
        resize: None,
    })
    .expect("hog");
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(w.threads)
        .build()
        .expect("pool");
    let extract = |set: &[Vec<u8>]| {
        let imgs: Vec<_> = set
            .iter()
            .map(|b| decode_image("x", b, u64::MAX).expect("decode"))
            .collect();
        pool.install(|| extract_batch(&spec, &imgs).expect("extract"))
    };
    let t = Instant::now();
    for _ in 0..w.rounds {
        for b in w.ingest_batches() {
            extract(b);
        }
    }
    let no_store = w.rate(&w.refs, t.elapsed().as_secs_f64());
    let store_dir = tempfile::tempdir().expect("tempdir");
    let store = seasonloc_store::SledStore::open(store_dir.path()).expect("store");
    let t = Instant::now();
    for _ in 0..w.rounds {
        let map = store
            .create_map(seasonloc_app::store::NewMap {
                id: seasonloc_app::new_id().expect("an id"),
                name: "lib".into(),
                descriptor: seasonloc_app::model::DescriptorSettings::Hog {
                    cell_size: CELL,
                    resize: None,
                },
                idempotency: None,
            })
            .expect("map");
        for b in w.ingest_batches() {
            let m = extract(b);
            let metas = vec![seasonloc_app::model::ImageMeta::default(); m.rows()];
            let batch =
                seasonloc_app::store::ImageBatch::new(map.id, m, metas).expect("one meta per row");
            store.append_images(&batch).expect("append");
        }
    }
    let ingest = w.rate(&w.refs, t.elapsed().as_secs_f64());
    let reference = extract(&w.refs);
    let t = Instant::now();
    for _ in 0..w.rounds {
        for b in w.query_batches() {
            let q = extract(b);
            pool.install(|| localize(&q, &reference, &options()))
                .expect("localize");
        }
    }
    let localize = w.rate(&w.queries, t.elapsed().as_secs_f64());
    (no_store, Rates { ingest, localize })
}

/// The use cases in process: `CLIENTS` concurrent tasks, each appending to its own map, then
/// localizing against a map holding the references once. Returns the rates, the median
/// latency of one localize at a time (ms) for each of [`LATENCY_SIZES`], and the CPU time per
/// localized image (ms, every thread of the process).
fn use_case_rates(w: &Workload) -> (Rates, Vec<f64>, f64) {
    let dir = tempfile::tempdir().expect("tempdir");
    let app = Arc::new(use_cases(dir.path(), w.threads));
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let hog = || NewMapSpec {
        name: "m".into(),
        descriptor: DescriptorSpec::Settings(seasonloc_app::model::DescriptorSettings::Hog {
            cell_size: CELL,
            resize: None,
        }),
    };
    let maps: Arc<Vec<u64>> = Arc::new(
        (0..=CLIENTS)
            .map(|_| rt.block_on(app.create_map(hog(), None)).expect("map").0.id)
            .collect(),
    );
    // Fetched per request, as the API does (the map's image count moves).
    let append = |app: Arc<App>, map: u64, batch: Vec<ImageInput>| async move {
        let metas = vec![seasonloc_app::model::ImageMeta::default(); batch.len()];
        let target = app.map_for(map, Upload::Images).await.expect("map");
        app.append_images(target, batch, metas, None)
            .await
            .expect("append");
    };
    let batches: Arc<Vec<Vec<ImageInput>>> =
        Arc::new(w.ingest_batches().into_iter().map(inputs).collect());
    let target = maps[CLIENTS];
    for b in batches.iter() {
        rt.block_on(append(Arc::clone(&app), target, b.clone()));
    }
    let secs = {
        let (app, maps, batches) = (Arc::clone(&app), Arc::clone(&maps), Arc::clone(&batches));
        concurrently(CLIENTS, w.rounds * batches.len(), move |k, j| {
            append(
                Arc::clone(&app),
                maps[k],
                batches[j % batches.len()].clone(),
            )
        })
    };
    let ingest = w.rate(&w.refs, secs);
    let queries: Arc<Vec<Vec<ImageInput>>> =
        Arc::new(w.query_batches().into_iter().map(inputs).collect());
    let request = move |j: usize| LocalizeInput {
        queries: Queries::Images(queries[j % queries.len()].clone()),
        options: options(),
        method: None,
    };
    let batches = w.query_batches().len();
    let cpu = process_cpu_secs();
    let secs = {
        let (app, request) = (Arc::clone(&app), request.clone());
        concurrently(CLIENTS, w.rounds * batches, move |_, j| {
            let (app, input) = (Arc::clone(&app), request(j));
            async move {
                app.localize(target, input, None, || {})
                    .await
                    .expect("localize");
            }
        })
    };
    let cpu = process_cpu_secs() - cpu;
    let localize = w.rate(&w.queries, secs);
    let localize_cpu = 1e3 * cpu / (w.rounds * w.queries.len()) as f64;
    let latency = LATENCY_SIZES
        .iter()
        .map(|&k| {
            median_ms((0..LATENCY_REQUESTS).map(|j| {
                let mut input = request(j);
                if let Queries::Images(images) = &mut input.queries {
                    images.truncate(k);
                }
                let t = Instant::now();
                rt.block_on(app.localize(target, input, None, || {}))
                    .expect("localize");
                t.elapsed()
            }))
        })
        .collect();
    (Rates { ingest, localize }, latency, localize_cpu)
}

/// What the HTTP run measured besides its rates.
struct HttpRun {
    rates: Rates,
    /// Median latency of one localize at a time on a kept connection, for each of
    /// [`LATENCY_SIZES`], and of a full batch on a new connection.
    latency: Vec<f64>,
    latency_close: f64,
    /// CPU seconds the clients used during the localize phase, and its length.
    client_cpu: f64,
    localize_secs: f64,
    /// The server's CPU time per localized image (ms; the process's less the clients').
    localize_cpu: f64,
}

/// The running service: `CLIENTS` client threads on kept connections, each uploading batches
/// to its own map, then localizing batches; then one localize at a time.
fn over_http(w: &Workload) -> HttpRun {
    let (client, stop, handle, _dir) = start_server(w.threads);
    let new_map = |name: &str| -> String {
        let r = client.post_json(
            "/v1/maps",
            &serde_json::json!({"name": name, "descriptor": {"kind": "hog", "cell_size": CELL}}),
        );
        r.json()["id"].as_str().expect("id").to_string()
    };
    let maps: Vec<String> = (0..CLIENTS).map(|k| new_map(&format!("m{k}"))).collect();
    let bodies: Vec<Vec<u8>> = w
        .ingest_batches()
        .iter()
        .map(|b| http::multipart_body(&parts(b)))
        .collect();
    let ct = format!("multipart/form-data; boundary={}", http::BOUNDARY);
    // Each client posts every `CLIENTS`-th batch of `rounds` passes to `path(k)`; the CPU
    // seconds the clients used.
    let run = |path: &dyn Fn(usize) -> String, bodies: &[Vec<u8>]| -> f64 {
        let cpu = std::sync::Mutex::new(0.0f64);
        std::thread::scope(|s| {
            for k in 0..CLIENTS {
                let (path, cpu, ct) = (path(k), &cpu, &ct);
                s.spawn(move || {
                    let start = thread_cpu_secs();
                    let mut conn = KeepAlive::connect(client.addr);
                    for j in (k..w.rounds * bodies.len()).step_by(CLIENTS) {
                        let (status, body) = conn.post(&path, ct, &bodies[j % bodies.len()]);
                        assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
                    }
                    *cpu.lock().expect("a sum") += thread_cpu_secs() - start;
                });
            }
        });
        cpu.into_inner().expect("a sum")
    };
    let t = Instant::now();
    run(&|k| format!("/v1/maps/{}/images", maps[k]), &bodies);
    let ingest = w.rate(&w.refs, t.elapsed().as_secs_f64());
    // A map holding the references exactly once, to localize against.
    let target = new_map("target");
    for b in &bodies {
        let r = client.request("POST", &format!("/v1/maps/{target}/images"), Some(&ct), b);
        assert_eq!(r.status, 200);
    }
    let params = Part::json("params", &serde_json::json!({"hidden_cost": 1.3}));
    let query_bodies = |k: usize| -> Vec<Vec<u8>> {
        w.query_batches()
            .iter()
            .map(|b| {
                let mut p = parts(&b[..k.min(b.len())]);
                p.push(Part {
                    name: params.name.clone(),
                    file_name: None,
                    content_type: params.content_type.clone(),
                    bytes: params.bytes.clone(),
                });
                http::multipart_body(&p)
            })
            .collect()
    };
    let qbodies = query_bodies(BATCH);
    let path = format!("/v1/maps/{target}/localize");
    let (t, cpu) = (Instant::now(), process_cpu_secs());
    let client_cpu = run(&|_| path.clone(), &qbodies);
    let localize_secs = t.elapsed().as_secs_f64();
    let server_cpu = process_cpu_secs() - cpu - client_cpu;
    let localize_cpu = 1e3 * server_cpu / (w.rounds * w.queries.len()) as f64;
    let localize = w.rate(&w.queries, localize_secs);
    let mut conn = KeepAlive::connect(client.addr);
    let latency = LATENCY_SIZES
        .iter()
        .map(|&k| {
            let bodies = query_bodies(k);
            median_ms((0..LATENCY_REQUESTS).map(|j| {
                let t = Instant::now();
                let (status, body) = conn.post(&path, &ct, &bodies[j % bodies.len()]);
                assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
                t.elapsed()
            }))
        })
        .collect();
    // The same through a new connection per request (`Connection: close`).
    let latency_close = median_ms((0..LATENCY_REQUESTS).map(|j| {
        let t = Instant::now();
        let r = client.request("POST", &path, Some(&ct), &qbodies[j % qbodies.len()]);
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        t.elapsed()
    }));
    let _ = stop.send(());
    handle.join().expect("server thread");
    HttpRun {
        rates: Rates { ingest, localize },
        latency,
        latency_close,
        client_cpu,
        localize_secs,
        localize_cpu,
    }
}

fn main() {
    // `cargo bench` passes `--bench`; any filter argument is ignored.
    let rounds: usize = std::env::var("SEASONLOC_BENCH_ROUNDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2);
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let (refs, queries, source) = images();
    let w = Workload {
        refs,
        queries,
        rounds,
        threads,
    };
    let (no_store, lib) = algorithms_alone(&w);
    let (uc, uc_latency, uc_cpu) = use_case_rates(&w);
    let web = over_http(&w);

    println!("service benchmark: {source}, {} references, {} queries, batches of {BATCH}, {rounds} rounds, {CLIENTS} HTTP clients, {threads} CPU threads, HOG {CELL} px", w.refs.len(), w.queries.len());
    println!();
    println!("| path | algorithms alone (images/s) | use cases, {CLIENTS} tasks (images/s) | HTTP, {CLIENTS} clients (images/s) | HTTP overhead over the use cases |");
    println!("| --- | --- | --- | --- | --- |");
    for (what, lib, uc, web) in [
        (
            "ingest (algorithms alone: decode + HOG + flushed store append)",
            lib.ingest,
            uc.ingest,
            web.rates.ingest,
        ),
        (
            "localize (algorithms alone: decode + HOG + similarity + solve + confidences)",
            lib.localize,
            uc.localize,
            web.rates.localize,
        ),
    ] {
        println!(
            "| {what} | {lib:.0} | {uc:.0} | {web:.0} | {:+.1} % |",
            (uc / web - 1.0) * 100.0
        );
    }
    println!();
    println!("decode + HOG alone, no store: {no_store:.0} images/s");
    println!(
        "HTTP localize: the clients used {:.2} s of CPU in {:.2} s on {threads} threads ({:.1} % \
         of the machine)",
        web.client_cpu,
        web.localize_secs,
        100.0 * web.client_cpu / (web.localize_secs * threads as f64)
    );
    println!(
        "CPU time per localized image: use cases {uc_cpu:.3} ms, HTTP server {:.3} ms ({:+.1} %)",
        web.localize_cpu,
        (web.localize_cpu / uc_cpu - 1.0) * 100.0
    );
    println!();
    println!(
        "one localize at a time, median of {LATENCY_REQUESTS} (ms; HTTP on a kept connection):"
    );
    println!("| images | use cases | HTTP | HTTP - use cases |");
    println!("| --- | --- | --- | --- |");
    for ((k, u), h) in LATENCY_SIZES.iter().zip(&uc_latency).zip(&web.latency) {
        println!("| {k} | {u:.3} | {h:.3} | {:+.3} |", h - u);
    }
    println!(
        "{BATCH} images with a new connection per request: HTTP {:.3} ms",
        web.latency_close
    );
}
