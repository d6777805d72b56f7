//! Where the service's logs and traces go: `tracing` events on stderr, as text lines or as one
//! JSON object per line (`--log-format`, [`LogFormat`]), and, with `--otlp-endpoint` (env
//! `OTEL_EXPORTER_OTLP_ENDPOINT`), the spans as OpenTelemetry traces over OTLP/HTTP.
//!
//! The JSON form is for log shippers (Loki, Elasticsearch): `timestamp`, `level`, `target`,
//! the event's fields flattened beside its `message`, and under `span` the fields of the
//! request it belongs to (`request_id`, `method`, `route`, `key`). The per-request line itself
//! ([`crate::api::access_log`]) carries every field at the top level. Secrets never reach an
//! event: keys are logged by name, database URLs are redacted by their type.
//!
//! Traces (the well-kept `opentelemetry` SDK, its OTLP exporter and `tracing-opentelemetry`):
//! each request is a server span named `METHOD /route/template` with the request's fields (ids
//! included) as attributes; the use cases' spans (`describe`, `similarity`, `solve`, one
//! `store` span per store call) are its children. A W3C `traceparent` header in a request
//! makes its span a child of the caller's, and every response carries the `traceparent` of its
//! span. Spans leave in batches from a background thread (JSON over HTTP), so a slow or absent
//! collector never delays a request; [`Telemetry::shutdown`] sends what is left at exit.

use std::sync::atomic::{AtomicBool, Ordering};

use axum::http::{HeaderMap, HeaderName, HeaderValue};
use opentelemetry::propagation::{Extractor, Injector};
use opentelemetry::trace::TracerProvider as _;
use opentelemetry_otlp::{Protocol, WithExportConfig};
use opentelemetry_sdk::propagation::TraceContextPropagator;
use opentelemetry_sdk::trace::SdkTracerProvider;
use opentelemetry_sdk::Resource;
use tracing_opentelemetry::OpenTelemetrySpanExt;
use tracing_subscriber::filter::{LevelFilter, Targets};
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::{EnvFilter, Layer, Registry};

use crate::config::LogFormat;

/// Whether spans are exported (set once by [`init`]).
static TRACING: AtomicBool = AtomicBool::new(false);

/// Whether `--otlp-endpoint` turned traces on in this process.
pub fn tracing_enabled() -> bool {
    TRACING.load(Ordering::Relaxed)
}

/// The format used when none is asked for: text for a person at a terminal, JSON for a
/// container runtime or a file.
pub fn default_format() -> LogFormat {
    if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        LogFormat::Text
    } else {
        LogFormat::Json
    }
}

/// The trace pipeline of the process: keep it while serving, then [`Telemetry::shutdown`].
#[derive(Default)]
pub struct Telemetry {
    provider: Option<SdkTracerProvider>,
}

impl Telemetry {
    /// Sends the spans still buffered and stops the exporter (a no-op without traces).
    pub fn shutdown(self) {
        if let Some(p) = self.provider {
            if let Err(e) = p.shutdown() {
                tracing::warn!("sending the last spans: {e}");
            }
        }
    }
}

/// Installs the stderr logger (`RUST_LOG` filter, default `info`) in `format`, or the
/// [`default_format`], and the OTLP exporter when `otlp_endpoint` is given (a base URL such as
/// `http://collector:4318`; spans go to its `/v1/traces`), unless a logger is installed
/// already.
pub fn init(format: Option<LogFormat>, otlp_endpoint: Option<&str>) -> anyhow::Result<Telemetry> {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let fmt = fmt_layer(format.unwrap_or_else(default_format)).with_filter(filter);
    let endpoint = otlp_endpoint.map(str::trim).filter(|e| !e.is_empty());
    let Some(endpoint) = endpoint else {
        let _ = tracing_subscriber::registry().with(fmt).try_init();
        return Ok(Telemetry::default());
    };
    if !(endpoint.starts_with("http://") || endpoint.starts_with("https://")) {
        anyhow::bail!(
            "invalid setting `otlp_endpoint`: `{endpoint}` is not an http:// or https:// URL"
        );
    }
    let url = format!("{}/v1/traces", endpoint.trim_end_matches('/'));
    let exporter = opentelemetry_otlp::SpanExporter::builder()
        .with_http()
        .with_protocol(Protocol::HttpJson)
        .with_endpoint(url.clone())
        .build()
        .map_err(|e| anyhow::anyhow!("invalid setting `otlp_endpoint` ({url}): {e}"))?;
    let provider = SdkTracerProvider::builder()
        .with_batch_exporter(exporter)
        .with_resource(Resource::builder().with_service_name("seasonloc").build())
        .build();
    let tracer = provider.tracer("seasonloc");
    opentelemetry::global::set_text_map_propagator(TraceContextPropagator::new());
    // Only the service's own spans: the libraries' debug spans (hyper, the database driver)
    // would multiply the export for nothing an operator reads.
    let ours = Targets::new()
        .with_target("seasonloc_server", LevelFilter::INFO)
        .with_target("seasonloc_app", LevelFilter::INFO)
        .with_target("seasonloc_store", LevelFilter::INFO);
    let otel = tracing_opentelemetry::layer()
        .with_tracer(tracer)
        .with_filter(ours);
    let installed = tracing_subscriber::registry()
        .with(fmt)
        .with(otel)
        .try_init()
        .is_ok();
    TRACING.store(installed, Ordering::Relaxed);
    Ok(Telemetry {
        provider: Some(provider),
    })
}

/// The stderr layer in `format`.
fn fmt_layer(format: LogFormat) -> Box<dyn Layer<Registry> + Send + Sync> {
    let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
    match format {
        LogFormat::Text => tracing_subscriber::fmt::layer()
            .with_writer(std::io::stderr)
            .with_ansi(terminal)
            .boxed(),
        LogFormat::Json => tracing_subscriber::fmt::layer()
            .json()
            .flatten_event(true)
            .with_current_span(true)
            .with_span_list(false)
            .with_writer(std::io::stderr)
            .boxed(),
    }
}

struct Headers<'a>(&'a HeaderMap);

impl Extractor for Headers<'_> {
    fn get(&self, key: &str) -> Option<&str> {
        self.0.get(key).and_then(|v| v.to_str().ok())
    }

    fn keys(&self) -> Vec<&str> {
        self.0.keys().map(HeaderName::as_str).collect()
    }
}

struct HeadersMut<'a>(&'a mut HeaderMap);

impl Injector for HeadersMut<'_> {
    fn set(&mut self, key: &str, value: String) {
        if let (Ok(name), Ok(value)) = (
            HeaderName::from_bytes(key.as_bytes()),
            HeaderValue::from_str(&value),
        ) {
            self.0.insert(name, value);
        }
    }
}

/// Makes `span` a child of the trace a request's `traceparent` names (when traces are on).
pub fn adopt_parent(span: &tracing::Span, headers: &HeaderMap) {
    if !tracing_enabled() {
        return;
    }
    let cx = opentelemetry::global::get_text_map_propagator(|p| p.extract(&Headers(headers)));
    // A span already entered cannot change parent; this one is new.
    let _ = span.set_parent(cx);
}

/// Writes `span`'s `traceparent` into a response's headers (when traces are on).
pub fn inject_context(span: &tracing::Span, headers: &mut HeaderMap) {
    if !tracing_enabled() {
        return;
    }
    let cx = span.context();
    opentelemetry::global::get_text_map_propagator(|p| {
        p.inject_context(&cx, &mut HeadersMut(headers));
    });
}
