//! Test harness: servers (in-process on an ephemeral port, or the real binary), synthetic route
//! images, and the path of the shared Nordland data.

use std::io::Cursor;
use std::net::SocketAddr;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use seasonloc_server::config::ServeArgs;

use crate::http::Client;

#[path = "../support/nordland.rs"]
mod nordland;
pub use nordland::{nordland, nordland_files};

/// The service running in this process (its own runtime thread) on `127.0.0.1:0`.
pub struct Server {
    pub client: Client,
    _dir: tempfile::TempDir,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<anyhow::Result<()>>>,
}

impl Server {
    pub fn start() -> Server {
        Server::start_with(|_| {})
    }

    pub fn start_with(configure: impl FnOnce(&mut ServeArgs)) -> Server {
        let dir = tempfile::tempdir().unwrap();
        let mut args = ServeArgs {
            data_dir: dir.path().to_path_buf(),
            database_url: engine_database(),
            worker_threads: 2,
            ..ServeArgs::default()
        };
        configure(&mut args);
        let settings = args.validate().unwrap();
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        listener.set_nonblocking(true).unwrap();
        let addr = listener.local_addr().unwrap();
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let thread = std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .build()?;
            rt.block_on(async move {
                let listener = tokio::net::TcpListener::from_std(listener)?;
                seasonloc_server::service::serve(settings, listener, async move {
                    let _ = stopped.await;
                })
                .await
            })
        });
        let server = Server {
            client: Client::new(addr),
            _dir: dir,
            stop: Some(stop),
            thread: Some(thread),
        };
        server.wait_ready();
        server
    }

    fn wait_ready(&self) {
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if let Ok(r) = self.client.try_request("GET", "/readyz", None, &[]) {
                if r.status == 200 {
                    return;
                }
            }
            assert!(Instant::now() < deadline, "server did not become ready");
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Whether this test binary runs the service on PostgreSQL: the same test files are compiled
/// twice, as `service` (the embedded store) and `service_pg` (tests/service_pg/main.rs), so
/// every in-process server test runs against both engines.
pub fn on_postgres() -> bool {
    env!("CARGO_CRATE_NAME") == "service_pg"
}

/// A new database on this binary's PostgreSQL server when [`on_postgres`] (one server per test
/// process, one database per server started); `None` for the embedded store.
pub fn engine_database() -> Option<String> {
    if !on_postgres() {
        return None;
    }
    // Skips (ends this test process successfully, after saying why) when PostgreSQL is not
    // installed, except under CI=true, where `require` panics.
    if seasonloc_test_support::postgres::require("this service_pg test").is_none() {
        std::process::exit(0);
    }
    Some(
        seasonloc_test_support::postgres::shared()
            .and_then(|s| s.database())
            .unwrap_or_else(|e| panic!("cannot start the test PostgreSQL server: {e}")),
    )
}

/// The real `seasonloc serve` binary as a child process.
pub struct Process {
    pub child: Child,
    pub client: Client,
}

impl Process {
    /// Starts `seasonloc serve` on an ephemeral port with its store in `data`, stderr to `log`
    /// (the restart and SIGKILL tests start it again on the same folder).
    pub fn serve(data: &Path, log: &Path) -> Process {
        let data = data.to_string_lossy();
        Process::start(&["--addr", "127.0.0.1:0", "--data-dir", &data], &[], log)
    }

    /// Starts `seasonloc serve` with `args` and environment `env`, stderr to `log`, and waits
    /// for its "listening on" line.
    pub fn start(args: &[&str], env: &[(&str, &str)], log: &Path) -> Process {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_seasonloc"));
        cmd.arg("serve").args(args);
        Process::spawn(cmd, env, log)
    }

    /// [`Process::start`] through `sh shell... BINARY serve args...`, e.g. `["-c", "ulimit -n
    /// \"$0\" && exec \"$@\"", "256"]`: the shell sets a limit, then becomes the server (same
    /// pid).
    pub fn start_under(shell: &[&str], args: &[&str], env: &[(&str, &str)], log: &Path) -> Process {
        let mut cmd = Command::new("sh");
        cmd.args(shell)
            .arg(env!("CARGO_BIN_EXE_seasonloc"))
            .arg("serve")
            .args(args);
        Process::spawn(cmd, env, log)
    }

    fn spawn(mut cmd: Command, env: &[(&str, &str)], log: &Path) -> Process {
        let file = std::fs::File::create(log).unwrap();
        cmd.env_remove("SEASONLOC_ADDR")
            .env_remove("SEASONLOC_DATA_DIR")
            .env("RUST_LOG", "info")
            // The tests read the text form; tests/service/logs.rs reads the JSON one.
            .env("SEASONLOC_LOG_FORMAT", "text")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(file);
        for (k, v) in env {
            cmd.env(k, v);
        }
        let mut child = cmd.spawn().unwrap();
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let text = std::fs::read_to_string(log).unwrap_or_default();
            if let Some(addr) = listening_addr(&text) {
                return Process {
                    child,
                    client: Client::new(addr),
                };
            }
            if let Ok(Some(status)) = child.try_wait() {
                panic!("seasonloc serve exited with {status} before listening:\n{text}");
            }
            assert!(
                Instant::now() < deadline,
                "no 'listening on' line in:\n{text}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Whether the process is still running.
    pub fn alive(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// Sends SIGTERM and waits; returns whether it exited successfully.
    pub fn terminate(mut self) -> bool {
        // The shell's builtin `kill` exists wherever `sh` does (no procps needed).
        let status = Command::new("sh")
            .args(["-c", &format!("kill -TERM {}", self.child.id())])
            .status()
            .unwrap();
        assert!(status.success());
        let exit = self.child.wait().unwrap();
        exit.success()
    }

    /// SIGKILL: no chance to flush anything.
    pub fn kill(mut self) {
        self.child.kill().unwrap();
        let _ = self.child.wait();
    }
}

impl Drop for Process {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// The address in the "listening on http://ADDR" log line.
pub fn listening_addr(log: &str) -> Option<SocketAddr> {
    let rest = log.split("listening on http://").nth(1)?;
    let addr: String = rest
        .chars()
        .take_while(|c| !c.is_whitespace() && *c != '"')
        .collect();
    // Strip ANSI colour codes that a terminal-aware logger might add.
    let addr = addr.split('\u{1b}').next()?;
    addr.parse().ok()
}

/// A deterministic pseudo-random generator (no dependency needed).
pub struct Lcg(u64);

impl Lcg {
    pub fn new(seed: u64) -> Self {
        Lcg(seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407))
    }
    pub fn next(&mut self) -> u32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 33) as u32
    }
    pub fn below(&mut self, n: u32) -> u32 {
        self.next() % n
    }
}

/// Frame size of the generated route (Nordland's thumbnail size).
pub const FRAME: (u32, u32) = (64, 32);
/// Pixels the camera moves between frames.
pub const STEP: u32 = 8;

/// A synthetic route: a long skyline of random buildings. Reference frame `i` is the window at
/// `i * STEP`; the query ("other season") is the same window darker, with less contrast and
/// noise.
pub struct Route {
    width: u32,
    strip: Vec<u8>,
}

impl Route {
    pub fn new(frames: u32, seed: u64) -> Route {
        let (fw, fh) = FRAME;
        let width = fw + STEP * frames;
        let mut rng = Lcg::new(seed);
        let mut strip = vec![0u8; (width * fh) as usize];
        let mut x = 0;
        while x < width {
            let w = 2 + rng.below(9);
            let roof = 4 + rng.below(fh - 6);
            let shade = 40 + rng.below(200) as u8;
            let windows = rng.below(2) == 0;
            for xx in x..(x + w).min(width) {
                for y in 0..fh {
                    let sky = (230 - y * 3) as u8;
                    let v = if y < roof {
                        sky
                    } else if windows && (y % 4 == 1) && (xx % 3 == 1) {
                        shade / 3
                    } else {
                        shade
                    };
                    strip[(y * width + xx) as usize] = v;
                }
            }
            x += w;
        }
        Route { width, strip }
    }

    fn frame(&self, i: u32, query: bool, rng: &mut Lcg) -> image::GrayImage {
        let (fw, fh) = FRAME;
        image::GrayImage::from_fn(fw, fh, |x, y| {
            let v = f32::from(self.strip[(y * self.width + i * STEP + x) as usize]);
            let v = if query {
                v * 0.6 + 30.0 + (rng.below(21) as f32 - 10.0)
            } else {
                v
            };
            image::Luma([v.clamp(0.0, 255.0) as u8])
        })
    }

    /// PNG bytes of reference frame `i`.
    pub fn reference_png(&self, i: u32) -> Vec<u8> {
        png(&self.frame(i, false, &mut Lcg::new(0)))
    }

    /// PNG bytes of query frame `i` (seeded noise).
    pub fn query_png(&self, i: u32) -> Vec<u8> {
        png(&self.frame(i, true, &mut Lcg::new(u64::from(i) + 99)))
    }
}

pub fn png(img: &image::GrayImage) -> Vec<u8> {
    let mut out = Vec::new();
    img.write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png)
        .unwrap();
    out
}

/// How many of a trip's `estimates` (frame `i` of a generated route shows place `i`) name a
/// reference within one frame of the truth.
pub fn within_one_frame(estimates: &[serde_json::Value]) -> usize {
    estimates
        .iter()
        .enumerate()
        .filter(|(i, e)| {
            e["ref"]
                .as_i64()
                .is_some_and(|j| (j - *i as i64).abs() <= 1)
        })
        .count()
}

/// The descriptors the library computes for encoded images with `extractor` (each decoded with
/// [`seasonloc_core::features::decode_image`], no pixel limit): what the tests compare HTTP answers
/// with.
pub fn library_descriptors(
    extractor: &dyn seasonloc_core::features::Extractor,
    encoded: &[Vec<u8>],
) -> seasonloc_core::Matrix {
    let images: Vec<_> = encoded
        .iter()
        .enumerate()
        .map(|(i, b)| {
            seasonloc_core::features::decode_image(&format!("#{i}"), b, u64::MAX).unwrap()
        })
        .collect();
    seasonloc_core::features::extract_batch(extractor, &images).unwrap()
}

/// Creates a HOG map and returns its id.
pub fn create_hog_map(client: &Client, name: &str, cell_size: u32) -> String {
    let r = client.post_json(
        "/v1/maps",
        &serde_json::json!({"name": name, "descriptor": {"kind": "hog", "cell_size": cell_size}}),
    );
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    r.json()["id"].as_str().unwrap().to_string()
}

/// Creates a precomputed-descriptor map and returns its id.
pub fn create_vector_map(client: &Client, name: &str, dim: u32) -> String {
    let r = client.post_json(
        "/v1/maps",
        &serde_json::json!({"name": name, "descriptor": {"kind": "precomputed", "dim": dim}}),
    );
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    r.json()["id"].as_str().unwrap().to_string()
}
