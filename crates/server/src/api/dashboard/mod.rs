//! The dashboard: what the fleet's people look at in a browser, served by the binary itself.
//!
//! Four pages, each with its own URL so links can be shared: `/` (maps, open trips, latest
//! localizations), `/maps/{id}`, `/localizations/{id}` and `/trips/{id}`. Every page is the
//! same HTML shell; its script (`assets/dashboard/app.js`) reads the path, fetches the public
//! JSON API (`/v1/...`) and draws the page with SVG. The dashboard is therefore a plain client
//! of the API: it sees exactly what any other reader sees, and needs no route of its own
//! beyond its files.
//!
//! Invariants:
//! * every file is embedded at build time (`include_bytes!`); nothing is loaded from another
//!   host, there is no CDN and no JavaScript build step, so the dashboard works offline;
//! * the pages' Content-Security-Policy allows this origin only (`default-src 'self'`), so a
//!   browser refuses any request elsewhere even if a script tried;
//! * files are revalidated on every load (`Cache-Control: no-cache`) with a content hash as
//!   `ETag`, computed at compile time, so an upgraded server never mixes old and new scripts
//!   and an unchanged file costs a `304`.

use axum::extract::Path;
use axum::http::{header, HeaderMap, HeaderName, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;

use crate::api::error::{ApiError, IdKind};
use crate::api::state::AppState;
use crate::api::wire::parse_id;

/// The routes of the dashboard.
pub fn router() -> Router<AppState> {
    Router::new()
        .route("/", get(page))
        .route("/maps/{id}", get(map_page))
        .route("/localizations/{id}", get(localization_page))
        .route("/trips/{id}", get(trip_page))
        .route("/assets/{name}", get(asset))
}

/// One embedded file.
struct Asset {
    name: &'static str,
    content_type: &'static str,
    body: &'static [u8],
    etag: &'static str,
}

/// FNV-1a, 64 bits: a content hash the compiler evaluates, so each file's `ETag` costs nothing
/// at run time (collisions only cost a stale cache, and 64 bits make that negligible).
const fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut i = 0;
    while i < bytes.len() {
        h ^= bytes[i] as u64;
        h = h.wrapping_mul(0x0100_0000_01b3);
        i += 1;
    }
    h
}

/// `"` + 16 hex digits + `"` of a file's hash, built at compile time.
const fn etag_of(bytes: &[u8]) -> [u8; 18] {
    const HEX: &[u8; 16] = b"0123456789abcdef";
    let h = fnv1a(bytes);
    let mut out = [b'"'; 18];
    let mut i = 0;
    while i < 16 {
        out[1 + i] = HEX[((h >> (60 - 4 * i)) & 0xf) as usize];
        i += 1;
    }
    out
}

macro_rules! asset {
    ($name:literal, $content_type:expr) => {{
        const BODY: &[u8] = include_bytes!(concat!("../../../assets/dashboard/", $name));
        const ETAG: [u8; 18] = etag_of(BODY);
        Asset {
            name: $name,
            content_type: $content_type,
            body: BODY,
            etag: match std::str::from_utf8(&ETAG) {
                Ok(s) => s,
                Err(_) => panic!("an ETag is ASCII"),
            },
        }
    }};
}

const JS: &str = "text/javascript; charset=utf-8";

/// Every file the pages load (flat names under `/assets/`).
static ASSETS: &[Asset] = &[
    asset!("app.js", JS),
    asset!("api.js", JS),
    asset!("plot.js", JS),
    asset!("ui.js", JS),
    asset!("overview.js", JS),
    asset!("map.js", JS),
    asset!("localization.js", JS),
    asset!("trip.js", JS),
    asset!("thumbs.js", JS),
    asset!("route.js", JS),
    asset!("dashboard.css", "text/css; charset=utf-8"),
    asset!("favicon.svg", "image/svg+xml"),
];

/// The HTML shell of every page.
static SHELL: Asset = asset!("index.html", "text/html; charset=utf-8");

/// Same-origin only: scripts, styles, images (thumbnails, the matrix picture; `blob:` for
/// pictures fetched with a key header) and API calls. No inline script or style.
const CSP: &str = "default-src 'self'; script-src 'self'; style-src 'self'; \
    img-src 'self' blob: data:; connect-src 'self'; object-src 'none'; base-uri 'none'; \
    form-action 'none'; frame-ancestors 'none'";

fn serve(a: &Asset, headers: &HeaderMap, csp: bool) -> Response {
    let fresh = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == a.etag || t.trim() == "*"));
    let status = if fresh {
        StatusCode::NOT_MODIFIED
    } else {
        StatusCode::OK
    };
    let mut r = if fresh {
        status.into_response()
    } else {
        (status, a.body).into_response()
    };
    let h = r.headers_mut();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(a.content_type),
    );
    h.insert(header::ETAG, HeaderValue::from_static(a.etag));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    if csp {
        h.insert(
            header::CONTENT_SECURITY_POLICY,
            HeaderValue::from_static(CSP),
        );
        h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
        h.insert(
            HeaderName::from_static("cross-origin-opener-policy"),
            HeaderValue::from_static("same-origin"),
        );
    }
    r
}

/// Every page: the shell, whose script draws what the path names (an unknown id is shown as
/// the API's 404 message on the page).
async fn page(headers: HeaderMap) -> Response {
    serve(&SHELL, &headers, true)
}

/// A page about one object: the shell when the path holds a well-formed id (whether it exists
/// is for the page to ask the API), the API's 404 when it cannot be an id at all.
fn object_page(id: &str, headers: &HeaderMap, not_found: IdKind) -> Result<Response, ApiError> {
    match parse_id(id) {
        Some(_) => Ok(serve(&SHELL, headers, true)),
        None => Err(ApiError::no_such_id(not_found, id)),
    }
}

async fn map_page(Path(id): Path<String>, headers: HeaderMap) -> Result<Response, ApiError> {
    object_page(&id, &headers, IdKind::Map)
}

async fn localization_page(
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    object_page(&id, &headers, IdKind::Localization)
}

async fn trip_page(Path(id): Path<String>, headers: HeaderMap) -> Result<Response, ApiError> {
    object_page(&id, &headers, IdKind::Trip)
}

async fn asset(Path(name): Path<String>, headers: HeaderMap) -> Result<Response, ApiError> {
    let a = ASSETS
        .iter()
        .find(|a| a.name == name)
        .ok_or(ApiError::AssetNotFound(name))?;
    Ok(serve(a, &headers, false))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn etags_are_quoted_hex_and_differ_per_file() {
        let mut seen = std::collections::HashSet::new();
        for a in ASSETS.iter().chain([&SHELL]) {
            assert_eq!(a.etag.len(), 18, "{}", a.name);
            assert!(a.etag.starts_with('"') && a.etag.ends_with('"'));
            assert!(a.etag[1..17].bytes().all(|b| b.is_ascii_hexdigit()));
            assert!(seen.insert(a.etag), "{} shares an ETag", a.name);
            assert!(!a.body.is_empty(), "{} is empty", a.name);
        }
        assert_eq!(fnv1a(b""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a(b"a"), 0xaf63_dc4c_8601_ec8c);
    }

    #[test]
    fn every_script_the_pages_import_is_served() {
        // Each `from "./x.js"` and `src="/assets/x"` must name an embedded file.
        let names: Vec<&str> = ASSETS.iter().map(|a| a.name).collect();
        for a in ASSETS.iter().chain([&SHELL]) {
            let text = std::str::from_utf8(a.body).expect("text asset");
            for quote in ["from \"./", "src=\"/assets/", "href=\"/assets/"] {
                for piece in text.split(quote).skip(1) {
                    let name = piece.split('"').next().unwrap_or("");
                    assert!(names.contains(&name), "{} refers to missing {name}", a.name);
                }
            }
        }
    }

    #[test]
    fn no_file_names_another_host() {
        for a in ASSETS.iter().chain([&SHELL]) {
            let text = String::from_utf8_lossy(a.body);
            for scheme in ["http://", "https://", "//cdn", "ws://", "wss://"] {
                let hits: Vec<&str> = text
                    .match_indices(scheme)
                    .map(|(i, _)| &text[i..(i + 40).min(text.len())])
                    // The SVG namespace is an identifier, never fetched.
                    .filter(|s| !s.starts_with("http://www.w3.org/"))
                    .collect();
                assert!(hits.is_empty(), "{} names {hits:?}", a.name);
            }
        }
    }

    #[test]
    fn content_types_match_extensions() {
        for a in ASSETS {
            let ext = a.name.rsplit('.').next().unwrap_or("");
            let want = match ext {
                "js" => JS,
                "css" => "text/css; charset=utf-8",
                "svg" => "image/svg+xml",
                other => panic!("no content type for .{other}"),
            };
            assert_eq!(a.content_type, want, "{}", a.name);
        }
    }
}
