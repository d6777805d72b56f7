//! Load benchmark of the HTTP path: images per second ingested and localized through the
//! running service with 8 concurrent clients, against the library doing the same work in
//! process (decode + HOG + localize on the same images, same CPU pool size).
//!
//! Run: `cargo bench --bench service` (`SEASONLOC_BENCH_ROUNDS` scales the work). Uses the
//! Nordland thumbnails from `../shared/data` when present, generated 64x32 frames otherwise.
//! Prints a markdown table; the overhead column is `library rate / HTTP rate - 1`. The HTTP
//! rates include everything the service does per request (multipart parsing, the store's
//! flushed write, storing the localization result).

#[path = "../tests/service/http.rs"]
#[allow(dead_code)]
mod http;

use std::io::Cursor;
use std::path::Path;
use std::time::Instant;

use http::{Client, Part};
use seasonloc::config::ServeArgs;
use seasonloc::features::hog::{HogOptions, HogSpec};
use seasonloc::features::{decode_image, extract_batch};
use seasonloc::localize::{localize, LocalizeOptions};
use seasonloc::solver::{HiddenCost, SolverParams};

const CLIENTS: usize = 8;
const BATCH: usize = 50;
const CELL: u32 = 8;

fn images() -> (Vec<Vec<u8>>, Vec<Vec<u8>>, &'static str) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = ["../shared", "../../shared"]
        .iter()
        .map(|s| root.join(s).join("data/nordland_64x32"))
        .find(|d| d.is_dir())
        .unwrap_or_else(|| root.join("../shared/data/nordland_64x32"));
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
        normalization: seasonloc::similarity::Normalization::default(),
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
    let settings = ServeArgs {
        data_dir: dir.path().to_path_buf(),
        worker_threads: threads,
        localize_queue: 64,
        ..ServeArgs::default()
    }
    .validate()
    .expect("settings");
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
            seasonloc::service::serve(settings, listener, async move {
                let _ = rx.await;
            })
            .await
            .expect("serve");
        });
    });
    (Client::new(addr), tx, handle, dir)
}

fn parts(images: &[Vec<u8>]) -> Vec<Part> {
    images
        .iter()
        .enumerate()
        .map(|(i, b)| Part::image(&format!("{i}.png"), b.clone()))
        .collect()
}

fn main() {
    // `cargo bench` passes `--bench`; any filter argument is ignored.
    let rounds: usize = std::env::var("SEASONLOC_BENCH_ROUNDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2);
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let (refs, queries, source) = images();
    let spec = HogSpec::new(HogOptions {
        cell_size: CELL,
        resize: None,
    })
    .expect("hog");
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("pool");

    // Library: the same batches, one after another, each extracted in parallel.
    let ingest_batches: Vec<&[Vec<u8>]> = refs.chunks(BATCH).collect();
    let extract = |set: &[Vec<u8>]| {
        let imgs: Vec<_> = set
            .iter()
            .map(|b| decode_image("x", b, u64::MAX).expect("decode"))
            .collect();
        extract_batch(&spec, &imgs).expect("extract")
    };
    let t = Instant::now();
    let mut n = 0;
    for _ in 0..rounds {
        for b in &ingest_batches {
            let m = pool.install(|| extract(b));
            n += m.rows();
        }
    }
    let lib_ingest = n as f64 / t.elapsed().as_secs_f64();
    // The same plus the store's atomic, flushed append of each batch: what the service does
    // besides HTTP.
    let store_dir = tempfile::tempdir().expect("tempdir");
    let store = seasonloc::store::SledStore::open(store_dir.path()).expect("store");
    let t = Instant::now();
    let mut n = 0;
    for _ in 0..rounds {
        let map = store
            .create_map(seasonloc::store::NewMap {
                id: seasonloc::app::new_id().expect("an id"),
                name: "lib".into(),
                descriptor: seasonloc::store::DescriptorSettings::Hog {
                    cell_size: CELL,
                    resize: None,
                },
                idempotency: None,
            })
            .expect("map");
        for b in &ingest_batches {
            let m = pool.install(|| extract(b));
            let rows = m.rows();
            let metas = vec![seasonloc::store::ImageMeta::default(); rows];
            let batch =
                seasonloc::store::ImageBatch::new(map.id, m, metas).expect("one meta per row");
            store.append_images(&batch).expect("append");
            n += rows;
        }
    }
    let lib_store_ingest = n as f64 / t.elapsed().as_secs_f64();
    drop(store);
    let reference = pool.install(|| extract(&refs));
    let query_batches: Vec<&[Vec<u8>]> = queries.chunks(BATCH).collect();
    let t = Instant::now();
    let mut n = 0;
    for _ in 0..rounds {
        for b in &query_batches {
            let q = pool.install(|| extract(b));
            pool.install(|| localize(&q, &reference, &options()))
                .expect("localize");
            n += q.rows();
        }
    }
    let lib_localize = n as f64 / t.elapsed().as_secs_f64();

    // HTTP: 8 clients, each uploading batches to its own map, then localizing batches.
    let (client, stop, handle, _dir) = start_server(threads);
    let maps: Vec<String> = (0..CLIENTS)
        .map(|k| {
            let r = client.post_json("/v1/maps", &serde_json::json!({"name": format!("m{k}"), "descriptor": {"kind": "hog", "cell_size": CELL}}));
            r.json()["id"].as_str().expect("id").to_string()
        })
        .collect();
    let bodies: Vec<Vec<u8>> = ingest_batches
        .iter()
        .map(|b| http::multipart_body(&parts(b)))
        .collect();
    let ct = format!("multipart/form-data; boundary={}", http::BOUNDARY);
    let t = Instant::now();
    // The batches of `rounds` passes over the references, spread over the clients.
    let jobs: Vec<usize> = (0..rounds * bodies.len()).collect();
    std::thread::scope(|s| {
        for k in 0..CLIENTS {
            let (jobs, bodies, maps, ct) = (&jobs, &bodies, &maps, &ct);
            s.spawn(move || {
                for j in jobs.iter().skip(k).step_by(CLIENTS) {
                    let r = client.request(
                        "POST",
                        &format!("/v1/maps/{}/images", maps[k]),
                        Some(ct),
                        &bodies[j % bodies.len()],
                    );
                    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
                }
            });
        }
    });
    let http_ingest = (rounds * refs.len()) as f64 / t.elapsed().as_secs_f64();
    // A map holding the references exactly once, to localize against.
    let target = client.post_json("/v1/maps", &serde_json::json!({"name": "target", "descriptor": {"kind": "hog", "cell_size": CELL}})).json()["id"]
        .as_str()
        .expect("id")
        .to_string();
    for b in &bodies {
        assert_eq!(
            client
                .request("POST", &format!("/v1/maps/{target}/images"), Some(&ct), b)
                .status,
            200
        );
    }
    let params = Part::json("params", &serde_json::json!({"hidden_cost": 1.3}));
    let qbodies: Vec<Vec<u8>> = query_batches
        .iter()
        .map(|b| {
            let mut p = parts(b);
            p.push(Part {
                name: params.name.clone(),
                file_name: None,
                content_type: params.content_type.clone(),
                bytes: params.bytes.clone(),
            });
            http::multipart_body(&p)
        })
        .collect();
    let jobs: Vec<usize> = (0..rounds * qbodies.len()).collect();
    let t = Instant::now();
    std::thread::scope(|s| {
        for k in 0..CLIENTS {
            let (jobs, qbodies, target, ct) = (&jobs, &qbodies, &target, &ct);
            s.spawn(move || {
                for j in jobs.iter().skip(k).step_by(CLIENTS) {
                    let r = client.request(
                        "POST",
                        &format!("/v1/maps/{target}/localize"),
                        Some(ct),
                        &qbodies[j % qbodies.len()],
                    );
                    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
                }
            });
        }
    });
    let http_localize = (rounds * queries.len()) as f64 / t.elapsed().as_secs_f64();
    let _ = stop.send(());
    handle.join().expect("server thread");

    println!("service benchmark: {source}, {} references, {} queries, batches of {BATCH}, {rounds} rounds, {CLIENTS} HTTP clients, {threads} CPU threads, HOG {CELL} px", refs.len(), queries.len());
    println!();
    println!("| path | library (images/s) | HTTP, {CLIENTS} clients (images/s) | HTTP overhead |");
    println!("| --- | --- | --- | --- |");
    for (what, lib, web) in [
        ("ingest: decode + HOG", lib_ingest, http_ingest),
        (
            "ingest: decode + HOG + flushed store append",
            lib_store_ingest,
            http_ingest,
        ),
        (
            "localize: decode + HOG + similarity + solve",
            lib_localize,
            http_localize,
        ),
    ] {
        println!(
            "| {what} | {lib:.0} | {web:.0} | {:+.1} % |",
            (lib / web - 1.0) * 100.0
        );
    }
}
