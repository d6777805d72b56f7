//! Wire types of the reads that show a map to people (`GET /v1/maps/{id}/images`).

use serde::{Deserialize, Serialize};

/// Query of `GET /v1/maps/{id}/images`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImagesQuery {
    /// First image index (default 0).
    pub from: Option<u32>,
    /// Most images (1..=1000, default 100).
    pub limit: Option<u32>,
}

/// One reference image's metadata.
#[derive(Clone, Debug, Serialize)]
pub struct ImageInfo {
    /// Route index.
    pub index: u32,
    /// Capture time as sent, or null.
    pub timestamp: Option<String>,
    /// Latitude in degrees, or null.
    pub latitude: Option<f64>,
    /// Longitude in degrees, or null.
    pub longitude: Option<f64>,
    /// Label as sent, or null.
    pub label: Option<String>,
}

/// A page of `GET /v1/maps/{id}/images`.
#[derive(Clone, Debug, Serialize)]
pub struct ImagePage {
    /// Images `from..` in route order.
    pub items: Vec<ImageInfo>,
    /// The map's image count.
    pub image_count: u32,
    /// Pass as `from` for the next page; null on the last page.
    pub next: Option<u32>,
}
