//! Shared state of the handlers: the use cases ([`App`]), the validated settings, the admission
//! slots of `/localize`, the metrics and the shipped OpenAPI document.
//!
//! Handlers never do CPU-heavy or blocking work themselves: they decode, call [`App`] (which
//! runs CPU work on its pool and awaits the store), and encode.

use std::sync::Arc;

use axum::body::Bytes;
use tokio::sync::Semaphore;

use super::metrics::Metrics;
use crate::app::App;
use crate::config::Settings;

/// Everything a handler needs; cheap to clone.
#[derive(Clone)]
pub struct AppState {
    /// The use cases.
    pub app: Arc<App>,
    /// Validated settings.
    pub settings: Arc<Settings>,
    /// Admission slots of `/localize` (running + waiting).
    pub localize_slots: Arc<Semaphore>,
    /// Prometheus metrics.
    pub metrics: Arc<Metrics>,
    /// `openapi/openapi.yaml` as JSON.
    pub openapi_json: Bytes,
}

impl AppState {
    /// Builds the state over the use cases.
    pub fn new(app: Arc<App>, settings: Settings) -> anyhow::Result<Self> {
        let openapi_json = Bytes::from(super::ops::openapi_json()?);
        Ok(AppState {
            app,
            localize_slots: Arc::new(Semaphore::new(settings.localize_queue)),
            settings: Arc::new(settings),
            metrics: Arc::new(Metrics::default()),
            openapi_json,
        })
    }
}
