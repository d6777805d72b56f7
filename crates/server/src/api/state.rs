//! Shared state of the handlers: the use cases ([`App`]), the validated settings, the admission
//! queue of `/localize`, the access control, the metrics and the shipped OpenAPI document.
//!
//! Handlers never do CPU-heavy or blocking work themselves: they decode, call [`App`] (which
//! runs CPU work on its pool and awaits the store), and encode.

use std::sync::Arc;

use axum::body::Bytes;

use super::admission::Admission;
use super::auth::Auth;
use super::metrics::Metrics;
use crate::config::Settings;
use seasonloc_app::App;

/// The OpenAPI document as shipped (served by `ops` at `/openapi.json`).
pub const OPENAPI_YAML: &str = include_str!("../../../../openapi/openapi.yaml");

/// The OpenAPI document converted to JSON.
pub fn openapi_json() -> anyhow::Result<Vec<u8>> {
    let doc: serde_json::Value = serde_yaml::from_str(OPENAPI_YAML)?;
    Ok(serde_json::to_vec(&doc)?)
}

/// Everything a handler needs; cheap to clone.
#[derive(Clone)]
pub struct AppState {
    /// The use cases.
    pub app: Arc<App>,
    /// Validated settings.
    pub settings: Arc<Settings>,
    /// Admission of `/localize`: a bounded FIFO queue in front of the CPU pool.
    pub admission: Arc<Admission>,
    /// Prometheus metrics.
    pub metrics: Arc<Metrics>,
    /// `openapi/openapi.yaml` as JSON.
    pub openapi_json: Bytes,
    /// Access control (`None`: every request is let through, see `--api-keys`).
    pub auth: Option<Arc<Auth>>,
}

impl AppState {
    /// Loads the API key file when one is configured. The service calls it before it opens its
    /// store, so that a missing or broken key file stops it before any side effect (a new data
    /// folder, a schema migration).
    pub fn load_auth(settings: &Settings) -> anyhow::Result<Option<Arc<Auth>>> {
        Ok(match &settings.api_keys {
            Some(path) => Some(Arc::new(Auth::load(path, settings.max_requests_per_key)?)),
            None => None,
        })
    }

    /// Builds the state over the use cases with the access control `auth` ([`Self::load_auth`]).
    pub fn new(app: Arc<App>, settings: Settings, auth: Option<Arc<Auth>>) -> anyhow::Result<Self> {
        Self::with_metrics(app, settings, auth, Arc::new(Metrics::default()))
    }

    /// [`Self::new`] recording into `metrics` (shared with the store's timing wrapper,
    /// [`seasonloc_app::timed_store::TimedStore`]).
    pub fn with_metrics(
        app: Arc<App>,
        settings: Settings,
        auth: Option<Arc<Auth>>,
        metrics: Arc<Metrics>,
    ) -> anyhow::Result<Self> {
        let openapi_json = Bytes::from(openapi_json()?);
        Ok(AppState {
            auth,
            app,
            admission: Arc::new(Admission::new(
                settings.localize_queue,
                settings.worker_threads,
                settings.localize_max_wait,
            )),
            settings: Arc::new(settings),
            metrics,
            openapi_json,
        })
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_shipped_spec_parses() {
        let json = super::openapi_json().unwrap();
        let v: serde_json::Value = serde_json::from_slice(&json).unwrap();
        assert!(v["openapi"].as_str().unwrap().starts_with("3."));
    }
}
