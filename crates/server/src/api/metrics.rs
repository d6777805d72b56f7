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
//!   `seasonloc_localize_rejected_total`.

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

#[derive(Clone, Debug, Default)]
struct Histogram {
    counts: [u64; BUCKETS.len()],
    sum: f64,
    count: u64,
}

impl Histogram {
    fn observe(&mut self, v: f64) {
        for (c, b) in self.counts.iter_mut().zip(BUCKETS) {
            if v <= b {
                *c += 1;
            }
        }
        self.sum += v;
        self.count += 1;
    }

    fn render(&self, out: &mut String, name: &str, labels: &str) {
        let sep = if labels.is_empty() { "" } else { "," };
        for (c, b) in self.counts.iter().zip(BUCKETS) {
            let _ = writeln!(out, "{name}_bucket{{{labels}{sep}le=\"{b}\"}} {c}");
        }
        let _ = writeln!(
            out,
            "{name}_bucket{{{labels}{sep}le=\"+Inf\"}} {}",
            self.count
        );
        let _ = writeln!(out, "{name}_sum{{{labels}}} {}", self.sum);
        let _ = writeln!(out, "{name}_count{{{labels}}} {}", self.count);
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

    /// The exposition text.
    pub fn render(&self) -> String {
        let m = self.lock();
        let mut out = String::new();
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
        let text = m.render();
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
