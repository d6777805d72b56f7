//! Prometheus metrics in the text exposition format, hand-written (a few counters and
//! histograms do not need a metrics framework).
//!
//! * `seasonloc_http_requests_total{method,route,status}` and
//!   `seasonloc_http_request_duration_seconds{method,route}` (histogram), recorded by
//!   [`track`] for every request, before authentication. Every label comes from a closed set,
//!   so no client can grow the label space: `method` is one of HTTP's standard methods or
//!   `other` ([`method_label`]), `route` the matched route template (ids do not explode it) or
//!   `unmatched`, `status` a three-digit status;
//! * `seasonloc_http_requests_by_key_total{key,status}`: requests that presented a known API
//!   key, by the key's `name` (never the key itself);
//! * `seasonloc_stage_duration_seconds{stage}` (histogram): `features`, `load_references`,
//!   `similarity`, `solve`, `store`;
//! * `seasonloc_images_ingested_total`, `seasonloc_queries_localized_total`,
//!   `seasonloc_localize_rejected_total`;
//! * the fleet: `seasonloc_trip_batches_total`, `seasonloc_trip_frames_total`,
//!   `seasonloc_trip_batch_duration_seconds` (histogram), `seasonloc_trip_frames_by_status_total
//!   {status}` (`localized`, `uncertain`, `off_map`, `lost`), `seasonloc_trip_frame_confidence`
//!   (histogram of each new frame's `p_correct`), and, read at scrape time by the `/metrics`
//!   handler, `seasonloc_trips_open{status}` (from the store: the same on every replica, so
//!   aggregate it with `max`, not `sum`) and `seasonloc_descriptor_cache_{maps,bytes}
//!   {descriptor}` (this process's cache, by descriptor kind);
//! * `seasonloc_localize_queue_wait_seconds` (histogram of the wait for a CPU turn);
//! * `seasonloc_store_operation_duration_seconds{operation}` (histogram, one series per
//!   method of the store trait) and `seasonloc_store_errors_total{operation}`;
//! * `seasonloc_build_info{version,commit}` and the process families of the Prometheus client
//!   libraries (`process_resident_memory_bytes`, `process_cpu_seconds_total`, ...; Linux,
//!   from `/proc`, [`process_metrics`]).
//!
//! No label carries an id or a client's string: every label value is from a closed set.

use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Instant;

use axum::extract::{MatchedPath, Request, State};
use axum::http::Method;
use axum::middleware::Next;
use axum::response::Response;

use super::auth::KeyName;

/// Upper bounds of the latency buckets, in seconds.
const BUCKETS: [f64; 14] = [
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

/// Upper bounds of the confidence buckets (`p_correct` is in 0..=1).
const UNIT_BUCKETS: [f64; 10] = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0];

#[derive(Clone, Debug)]
struct Histogram {
    bounds: &'static [f64],
    counts: Vec<u64>,
    sum: f64,
    count: u64,
}

impl Default for Histogram {
    fn default() -> Self {
        Histogram::with_bounds(&BUCKETS)
    }
}

impl Histogram {
    fn with_bounds(bounds: &'static [f64]) -> Self {
        Histogram {
            bounds,
            counts: vec![0; bounds.len()],
            sum: 0.0,
            count: 0,
        }
    }

    fn observe(&mut self, v: f64) {
        for (c, b) in self.counts.iter_mut().zip(self.bounds) {
            if v <= *b {
                *c += 1;
            }
        }
        self.sum += v;
        self.count += 1;
    }

    fn render(&self, out: &mut String, name: &str, labels: &str) {
        let sep = if labels.is_empty() { "" } else { "," };
        for (c, b) in self.counts.iter().zip(self.bounds) {
            let _ = writeln!(out, "{name}_bucket{{{labels}{sep}le=\"{b}\"}} {c}");
        }
        let _ = writeln!(
            out,
            "{name}_bucket{{{labels}{sep}le=\"+Inf\"}} {}",
            self.count
        );
        let braced = if labels.is_empty() {
            String::new()
        } else {
            format!("{{{labels}}}")
        };
        let _ = writeln!(out, "{name}_sum{braced} {}", self.sum);
        let _ = writeln!(out, "{name}_count{braced} {}", self.count);
    }
}

#[derive(Debug, Default)]
struct Inner {
    requests: BTreeMap<(String, String, u16), u64>,
    latency: BTreeMap<(String, String), Histogram>,
    by_key: BTreeMap<(String, u16), u64>,
    stages: BTreeMap<&'static str, Histogram>,
    images_ingested: u64,
    queries_localized: u64,
    localize_rejected: u64,
    trip_batches: u64,
    trip_frames: u64,
    trip_batch_latency: Histogram,
    frames_by_status: BTreeMap<&'static str, u64>,
    confidence: Option<Histogram>,
    queue_wait: Histogram,
    store_calls: BTreeMap<&'static str, Histogram>,
    store_errors: BTreeMap<&'static str, u64>,
}

/// What the `/metrics` handler reads at scrape time and hands to [`Metrics::render`].
#[derive(Clone, Debug, Default)]
pub struct Snapshot {
    /// Open trips by status name (`new`, `localized`, `lost`, `relocalized`); `None` when the
    /// store could not be read.
    pub open_trips: Option<Vec<(&'static str, usize)>>,
    /// This process's descriptor cache: kind -> (maps, bytes).
    pub cache: BTreeMap<&'static str, (usize, usize)>,
    /// Localize requests holding a place in the queue (waiting or running).
    pub queue_depth: usize,
}

/// The service's metrics.
#[derive(Debug, Default)]
pub struct Metrics {
    inner: Mutex<Inner>,
}

impl Metrics {
    fn lock(&self) -> MutexGuard<'_, Inner> {
        // Counters stay meaningful after a panic elsewhere; keep using them.
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Records one finished request.
    pub fn observe_request(&self, method: &str, route: &str, status: u16, seconds: f64) {
        let mut m = self.lock();
        *m.requests
            .entry((method.to_string(), route.to_string(), status))
            .or_default() += 1;
        m.latency
            .entry((method.to_string(), route.to_string()))
            .or_default()
            .observe(seconds);
    }

    /// Counts one request of the API key named `key`.
    pub fn observe_key(&self, key: &str, status: u16) {
        *self
            .lock()
            .by_key
            .entry((key.to_string(), status))
            .or_default() += 1;
    }

    /// Records the duration of one pipeline stage.
    pub fn observe_stage(&self, stage: &'static str, seconds: f64) {
        self.lock()
            .stages
            .entry(stage)
            .or_default()
            .observe(seconds);
    }

    /// Counts reference images stored.
    pub fn add_images_ingested(&self, n: u64) {
        self.lock().images_ingested += n;
    }

    /// Counts query images (or descriptors) localized.
    pub fn add_queries_localized(&self, n: u64) {
        self.lock().queries_localized += n;
    }

    /// Counts a localize request turned away by the full queue.
    pub fn add_queue_rejection(&self) {
        self.lock().localize_rejected += 1;
    }

    /// Records the wait of a localize request for its CPU turn.
    pub fn observe_queue_wait(&self, seconds: f64) {
        self.lock().queue_wait.observe(seconds);
    }

    /// Records one applied trip batch: its duration, and each new frame's status and
    /// `p_correct` (`(status name, p_correct)`).
    pub fn observe_trip_batch(&self, seconds: f64, frames: &[(&'static str, f64)]) {
        let mut m = self.lock();
        m.trip_batches += 1;
        m.trip_frames += frames.len() as u64;
        m.trip_batch_latency.observe(seconds);
        for (status, p) in frames {
            *m.frames_by_status.entry(status).or_default() += 1;
            if p.is_finite() {
                m.confidence
                    .get_or_insert_with(|| Histogram::with_bounds(&UNIT_BUCKETS))
                    .observe(p.clamp(0.0, 1.0));
            }
        }
    }

    /// The exposition text, with what the handler read at scrape time.
    pub fn render(&self, snapshot: &Snapshot) -> String {
        let m = self.lock();
        let mut out = String::new();
        render_fleet(&m, snapshot, &mut out);
        render_process(&mut out);
        out.push_str(
            "# HELP seasonloc_http_requests_total HTTP requests by method, route and status.\n",
        );
        out.push_str("# TYPE seasonloc_http_requests_total counter\n");
        for ((method, route, status), n) in &m.requests {
            let _ = writeln!(
                out,
                "seasonloc_http_requests_total{{method=\"{method}\",route=\"{}\",status=\"{status}\"}} {n}",
                escape(route)
            );
        }
        out.push_str("# HELP seasonloc_http_request_duration_seconds HTTP request latency.\n");
        out.push_str("# TYPE seasonloc_http_request_duration_seconds histogram\n");
        for ((method, route), h) in &m.latency {
            let labels = format!("method=\"{method}\",route=\"{}\"", escape(route));
            h.render(&mut out, "seasonloc_http_request_duration_seconds", &labels);
        }
        out.push_str(
            "# HELP seasonloc_http_requests_by_key_total HTTP requests by API key name and status.\n",
        );
        out.push_str("# TYPE seasonloc_http_requests_by_key_total counter\n");
        for ((key, status), n) in &m.by_key {
            let _ = writeln!(
                out,
                "seasonloc_http_requests_by_key_total{{key=\"{}\",status=\"{status}\"}} {n}",
                escape(key)
            );
        }
        out.push_str("# HELP seasonloc_stage_duration_seconds Time per pipeline stage.\n");
        out.push_str("# TYPE seasonloc_stage_duration_seconds histogram\n");
        for (stage, h) in &m.stages {
            h.render(
                &mut out,
                "seasonloc_stage_duration_seconds",
                &format!("stage=\"{stage}\""),
            );
        }
        for (name, help, v) in [
            (
                "seasonloc_images_ingested_total",
                "Reference images stored.",
                m.images_ingested,
            ),
            (
                "seasonloc_queries_localized_total",
                "Query images localized.",
                m.queries_localized,
            ),
            (
                "seasonloc_localize_rejected_total",
                "Localize requests refused by the queue (full, or the wait would exceed its bound).",
                m.localize_rejected,
            ),
        ] {
            let _ = writeln!(
                out,
                "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}"
            );
        }
        out
    }
}

/// Frame statuses, in the order they are listed (present from the start, at 0, so a rate
/// over them is defined before the first frame of each).
const FRAME_STATUSES: [&str; 4] = ["localized", "uncertain", "off_map", "lost"];

fn render_fleet(m: &Inner, snapshot: &Snapshot, out: &mut String) {
    let _ = writeln!(
        out,
        "# HELP seasonloc_build_info The running build (value 1).\n# TYPE seasonloc_build_info gauge\n\
         seasonloc_build_info{{version=\"{}\",commit=\"{}\"}} 1",
        env!("CARGO_PKG_VERSION"),
        escape(BUILD_COMMIT)
    );
    if let Some(open) = &snapshot.open_trips {
        out.push_str(
            "# HELP seasonloc_trips_open Open trips of the store by the status of their last batch.\n\
             # TYPE seasonloc_trips_open gauge\n",
        );
        for (status, n) in open {
            let _ = writeln!(out, "seasonloc_trips_open{{status=\"{status}\"}} {n}");
        }
    }
    for (name, help, v) in [
        (
            "seasonloc_trip_batches_total",
            "Trip batches applied.",
            m.trip_batches,
        ),
        (
            "seasonloc_trip_frames_total",
            "Trip frames applied.",
            m.trip_frames,
        ),
    ] {
        let _ = writeln!(
            out,
            "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}"
        );
    }
    out.push_str(
        "# HELP seasonloc_trip_batch_duration_seconds Time to apply one trip batch.\n\
         # TYPE seasonloc_trip_batch_duration_seconds histogram\n",
    );
    m.trip_batch_latency
        .render(out, "seasonloc_trip_batch_duration_seconds", "");
    out.push_str(
        "# HELP seasonloc_trip_frames_by_status_total Trip frames by their status at arrival.\n\
         # TYPE seasonloc_trip_frames_by_status_total counter\n",
    );
    for status in FRAME_STATUSES {
        let n = m.frames_by_status.get(status).copied().unwrap_or(0);
        let _ = writeln!(
            out,
            "seasonloc_trip_frames_by_status_total{{status=\"{status}\"}} {n}"
        );
    }
    out.push_str(
        "# HELP seasonloc_trip_frame_confidence p_correct of each trip frame at arrival.\n\
         # TYPE seasonloc_trip_frame_confidence histogram\n",
    );
    m.confidence
        .clone()
        .unwrap_or_else(|| Histogram::with_bounds(&UNIT_BUCKETS))
        .render(out, "seasonloc_trip_frame_confidence", "");
    let _ = writeln!(
        out,
        "# HELP seasonloc_localize_queue_depth Localize requests holding a place in the queue.\n\
         # TYPE seasonloc_localize_queue_depth gauge\nseasonloc_localize_queue_depth {}",
        snapshot.queue_depth
    );
    out.push_str(
        "# HELP seasonloc_localize_queue_wait_seconds Wait of a localize request for its CPU turn.\n\
         # TYPE seasonloc_localize_queue_wait_seconds histogram\n",
    );
    m.queue_wait
        .render(out, "seasonloc_localize_queue_wait_seconds", "");
    out.push_str(
        "# HELP seasonloc_store_operation_duration_seconds Store calls by operation.\n\
         # TYPE seasonloc_store_operation_duration_seconds histogram\n",
    );
    for (op, h) in &m.store_calls {
        h.render(
            out,
            "seasonloc_store_operation_duration_seconds",
            &format!("operation=\"{op}\""),
        );
    }
    out.push_str(
        "# HELP seasonloc_store_errors_total Failed store calls by operation.\n\
         # TYPE seasonloc_store_errors_total counter\n",
    );
    for (op, n) in &m.store_errors {
        let _ = writeln!(
            out,
            "seasonloc_store_errors_total{{operation=\"{op}\"}} {n}"
        );
    }
    out.push_str(
        "# HELP seasonloc_descriptor_cache_maps Maps whose descriptors this process caches.\n\
         # TYPE seasonloc_descriptor_cache_maps gauge\n",
    );
    for (kind, (maps, _)) in &snapshot.cache {
        let _ = writeln!(
            out,
            "seasonloc_descriptor_cache_maps{{descriptor=\"{kind}\"}} {maps}"
        );
    }
    out.push_str(
        "# HELP seasonloc_descriptor_cache_bytes Bytes of the cached descriptor matrices.\n\
         # TYPE seasonloc_descriptor_cache_bytes gauge\n",
    );
    for (kind, (_, bytes)) in &snapshot.cache {
        let _ = writeln!(
            out,
            "seasonloc_descriptor_cache_bytes{{descriptor=\"{kind}\"}} {bytes}"
        );
    }
}

/// The commit the binary was built from (`SEASONLOC_BUILD_COMMIT` at build time, else what
/// `git` said then, else `unknown`; see `build.rs`).
pub const BUILD_COMMIT: &str = env!("SEASONLOC_BUILD_COMMIT");

/// The process families of the Prometheus client libraries, read from `/proc/self` (nothing
/// where it cannot be read, e.g. off Linux).
pub fn process_metrics() -> Vec<(&'static str, &'static str, &'static str, f64)> {
    let mut out = Vec::new();
    // Linux reports CPU times in USER_HZ ticks, 100 a second on every architecture.
    const TICKS: f64 = 100.0;
    if let Ok(status) = std::fs::read_to_string("/proc/self/status") {
        for (key, name, help) in [
            (
                "VmRSS:",
                "process_resident_memory_bytes",
                "Resident memory size in bytes.",
            ),
            (
                "VmSize:",
                "process_virtual_memory_bytes",
                "Virtual memory size in bytes.",
            ),
        ] {
            let kb = status
                .lines()
                .find(|l| l.starts_with(key))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse::<f64>().ok());
            if let Some(kb) = kb {
                out.push((name, "gauge", help, kb * 1024.0));
            }
        }
    }
    if let Ok(stat) = std::fs::read_to_string("/proc/self/stat") {
        // Fields after the command name (which may hold spaces) in parentheses.
        let fields: Vec<&str> = stat
            .rsplit_once(')')
            .map_or(Vec::new(), |(_, rest)| rest.split_whitespace().collect());
        let num = |i: usize| fields.get(i).and_then(|v| v.parse::<f64>().ok());
        // utime and stime are fields 14 and 15 of stat(5), starttime 22: indices 11, 12, 19
        // after the state field (index 0 is field 3).
        if let (Some(u), Some(s)) = (num(11), num(12)) {
            out.push((
                "process_cpu_seconds_total",
                "counter",
                "User and system CPU time in seconds.",
                (u + s) / TICKS,
            ));
        }
        let boot = std::fs::read_to_string("/proc/stat").ok().and_then(|t| {
            t.lines()
                .find_map(|l| l.strip_prefix("btime "))
                .and_then(|v| v.trim().parse::<f64>().ok())
        });
        if let (Some(start), Some(boot)) = (num(19), boot) {
            out.push((
                "process_start_time_seconds",
                "gauge",
                "Start time of the process since the Unix epoch in seconds.",
                boot + start / TICKS,
            ));
        }
    }
    if let Ok(dir) = std::fs::read_dir("/proc/self/fd") {
        out.push((
            "process_open_fds",
            "gauge",
            "Open file descriptors.",
            dir.count() as f64,
        ));
    }
    if let Some(Some(n)) = crate::config::open_files_soft_limit() {
        out.push((
            "process_max_fds",
            "gauge",
            "Limit of open file descriptors.",
            n as f64,
        ));
    }
    out
}

fn render_process(out: &mut String) {
    for (name, kind, help, v) in process_metrics() {
        let _ = writeln!(
            out,
            "# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {v}"
        );
    }
}

impl seasonloc_app::timed_store::StoreObserver for Metrics {
    fn store_call(&self, operation: &'static str, seconds: f64, ok: bool) {
        let mut m = self.lock();
        m.store_calls.entry(operation).or_default().observe(seconds);
        if !ok {
            *m.store_errors.entry(operation).or_default() += 1;
        }
    }
}

fn escape(s: &str) -> String {
    s.replace('\\', "\\\\").replace('"', "\\\"")
}

/// The `method` label of a request: the standard method's name, or `other` for any extension
/// method (a client may send any token as a method, e.g. 1,000 characters of it, before it is
/// authenticated; each distinct one would otherwise be a new series kept forever). The log
/// span uses the same label.
pub fn method_label(method: &Method) -> &'static str {
    match *method {
        Method::GET => "GET",
        Method::HEAD => "HEAD",
        Method::POST => "POST",
        Method::PUT => "PUT",
        Method::DELETE => "DELETE",
        Method::OPTIONS => "OPTIONS",
        Method::PATCH => "PATCH",
        Method::TRACE => "TRACE",
        Method::CONNECT => "CONNECT",
        _ => "other",
    }
}

/// Middleware recording count and latency of every request under its matched route (its state
/// is the metrics alone, so this module does not depend on `state`).
pub async fn track(State(metrics): State<Arc<Metrics>>, req: Request, next: Next) -> Response {
    let started = Instant::now();
    let method = method_label(req.method());
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map_or_else(|| "unmatched".to_string(), |p| p.as_str().to_string());
    let response = next.run(req).await;
    if let Some(key) = response.extensions().get::<KeyName>() {
        metrics.observe_key(&key.0, response.status().as_u16());
    }
    metrics.observe_request(
        method,
        &route,
        response.status().as_u16(),
        started.elapsed().as_secs_f64(),
    );
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_counters_and_cumulative_buckets() {
        let m = Metrics::default();
        m.observe_request("GET", "/v1/maps/{id}", 200, 0.003);
        m.observe_request("GET", "/v1/maps/{id}", 200, 0.2);
        m.observe_stage("solve", 0.02);
        m.add_images_ingested(5);
        m.observe_key("car-7", 403);
        m.observe_trip_batch(0.04, &[("localized", 0.97), ("off_map", 0.0)]);
        let text = m.render(&Snapshot::default());
        assert!(text.contains("seasonloc_trip_frames_total 2"), "{text}");
        assert!(text.contains("seasonloc_trip_frames_by_status_total{status=\"off_map\"} 1"));
        assert!(text.contains("seasonloc_trip_frames_by_status_total{status=\"lost\"} 0"));
        assert!(text.contains("seasonloc_trip_frame_confidence_bucket{le=\"0.1\"} 1"));
        assert!(text.contains("seasonloc_trip_frame_confidence_bucket{le=\"+Inf\"} 2"));
        assert!(text.contains("seasonloc_build_info{version=\""));
        assert!(
            text.contains("seasonloc_http_requests_by_key_total{key=\"car-7\",status=\"403\"} 1")
        );
        assert!(text.contains(
            "seasonloc_http_requests_total{method=\"GET\",route=\"/v1/maps/{id}\",status=\"200\"} 2"
        ), "{text}");
        assert!(text.contains("seasonloc_http_request_duration_seconds_bucket{method=\"GET\",route=\"/v1/maps/{id}\",le=\"0.005\"} 1"));
        assert!(text.contains("seasonloc_http_request_duration_seconds_bucket{method=\"GET\",route=\"/v1/maps/{id}\",le=\"+Inf\"} 2"));
        assert!(text.contains("seasonloc_stage_duration_seconds_count{stage=\"solve\"} 1"));
        assert!(text.contains("seasonloc_images_ingested_total 5"));
    }

    #[test]
    fn extension_methods_share_one_label() {
        for m in ["GET", "POST", "DELETE", "OPTIONS"] {
            assert_eq!(method_label(&Method::from_bytes(m.as_bytes()).unwrap()), m);
        }
        let long = format!("M{}", "X".repeat(999));
        for m in ["PROPFIND", "get", long.as_str()] {
            assert_eq!(
                method_label(&Method::from_bytes(m.as_bytes()).unwrap()),
                "other"
            );
        }
    }
}
