//! Access control: API keys with roles (`reader` < `vehicle` < `admin`), the key file that lists
//! them, and the middleware that checks `Authorization: Bearer <key>` on every protected route.
//!
//! * The key file (`serve --api-keys FILE`) is JSON
//!   `{"keys": [{"name": "ops", "role": "admin", "sha256": "<hex sha256 of the key>"}]}`: the
//!   service never sees a key in clear except in the request that presents it, and never logs
//!   one. It is re-read on SIGHUP ([`Auth::reload`]); a file that does not parse keeps the old
//!   keys (the caller logs why).
//! * A presented key is hashed and compared with **every** stored digest in constant time
//!   (`subtle`), so neither the comparison nor the scan order tells an attacker how close a
//!   guess was.
//! * Which role a request needs is a pure function of its method and matched route
//!   ([`required_access`]): `/healthz`, `/readyz`, `/openapi.json` and the dashboard's pages and
//!   assets (which hold no data; the page asks for a key and sends it as a bearer token) are
//!   public; every `GET` under `/v1` and `/metrics` needs `reader`; localizing and a trip's
//!   life cycle need `vehicle`; everything else (create, upload, delete) needs `admin`.
//! * Without a key (or with an unknown one) the answer is 401 `unauthorized` with
//!   `WWW-Authenticate: Bearer`; a known key without the right gets 403 `forbidden`.
//! * Each key may have at most `max_requests_per_key` requests in flight; beyond that 429
//!   `too_many_requests` with `Retry-After`, so one misbehaving vehicle cannot starve the fleet.
//! * The key's name and whether it is an admin go to the handlers as a request extension
//!   ([`seasonloc_app::caller::Caller`]): a trip is extended and closed only by the key that
//!   opened it, or an admin.
//! * The key's `name` goes into the request's log span (`key=...`) and, through a response
//!   extension ([`KeyName`]), into the per-key metrics counter.

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, RwLock};

use axum::extract::{MatchedPath, Request, State};
use axum::http::{header, Method};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};
use subtle::{ConditionallySelectable, ConstantTimeEq};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use super::error::ApiError;

/// What a key may do; each role includes the rights of the ones before it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Every `GET` (maps, localizations, trips, metrics).
    Reader,
    /// `reader` plus localize, opening trips, posting frames and closing trips.
    Vehicle,
    /// Everything: create, append images / descriptors / drives, delete.
    Admin,
}

impl Role {
    /// The role's name as written in the key file.
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Reader => "reader",
            Role::Vehicle => "vehicle",
            Role::Admin => "admin",
        }
    }
}

/// What a request needs to be let through.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Access {
    /// No key needed.
    Public,
    /// A key with at least this role.
    Role(Role),
}

/// Routes anyone may call: probes, the API description, and the dashboard's pages and assets
/// (they hold no data; the page fetches everything from `/v1` with the user's key).
const PUBLIC_ROUTES: &[&str] = &[
    "/healthz",
    "/readyz",
    "/openapi.json",
    "/",
    "/maps/{id}",
    "/localizations/{id}",
    "/trips/{id}",
    "/assets/{name}",
];

/// `POST` routes a `vehicle` may call.
const VEHICLE_POSTS: &[&str] = &[
    "/v1/maps/{id}/localize",
    "/v1/maps/{id}/trips",
    "/v1/trips/{id}/frames",
    "/v1/trips/{id}/close",
];

/// The access `method route` needs; `route` is the matched route template (`None` when no route
/// matched: such requests still need a key, so the 404 tells nothing to anonymous callers).
pub fn required_access(method: &Method, route: Option<&str>) -> Access {
    let read = *method == Method::GET || *method == Method::HEAD;
    match route {
        Some(r) if read && PUBLIC_ROUTES.contains(&r) => Access::Public,
        _ if read => Access::Role(Role::Reader),
        Some(r) if *method == Method::POST && VEHICLE_POSTS.contains(&r) => {
            Access::Role(Role::Vehicle)
        }
        _ => Access::Role(Role::Admin),
    }
}

/// A key file that cannot be used; the message names the file and the entry, never a key.
#[derive(Debug, thiserror::Error)]
#[error("API key file {path}: {reason}")]
pub struct KeyFileError {
    /// The file.
    pub path: String,
    /// What is wrong with it.
    pub reason: String,
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct KeyFile {
    keys: Vec<KeyEntry>,
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct KeyEntry {
    name: String,
    role: Role,
    sha256: String,
}

/// One accepted key: its name, role and the SHA-256 of the key.
#[derive(Clone, Debug)]
pub struct ApiKey {
    /// Shown in logs and metrics instead of the key.
    pub name: String,
    /// What the key may do.
    pub role: Role,
    digest: [u8; 32],
}

/// The set of accepted keys (one version of the key file).
#[derive(Clone, Debug, Default)]
pub struct KeyRing {
    keys: Vec<ApiKey>,
}

impl KeyRing {
    /// Parses the key file's text. `origin` names the file in error messages.
    pub fn parse(text: &str, origin: &str) -> Result<KeyRing, KeyFileError> {
        let err = |reason: String| KeyFileError {
            path: origin.to_string(),
            reason,
        };
        let de = &mut serde_json::Deserializer::from_str(text);
        let file: KeyFile = serde_path_to_error::deserialize(de).map_err(|e| {
            // serde's message for a bad `sha256` value would quote it; the value is a digest,
            // not a key, but keep messages to the path and the kind of problem.
            err(format!("at `{}`: {}", e.path(), e.inner()))
        })?;
        if file.keys.is_empty() {
            return Err(err("`keys` is empty; list at least one key".into()));
        }
        let mut names = HashSet::new();
        let mut digests = HashSet::new();
        let mut keys = Vec::with_capacity(file.keys.len());
        for (i, k) in file.keys.into_iter().enumerate() {
            let valid_name = !k.name.is_empty()
                && k.name.len() <= 64
                && k.name
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b"-_.@".contains(&b));
            if !valid_name {
                return Err(err(format!(
                    "keys[{i}].name must be 1 to 64 characters of A-Z a-z 0-9 - _ . @"
                )));
            }
            if !names.insert(k.name.clone()) {
                return Err(err(format!("keys[{i}].name `{}` is listed twice", k.name)));
            }
            let digest = parse_hex_digest(&k.sha256).ok_or_else(|| {
                err(format!(
                    "keys[{i}].sha256 (key `{}`) must be 64 hexadecimal digits",
                    k.name
                ))
            })?;
            if !digests.insert(digest) {
                return Err(err(format!(
                    "keys[{i}] (key `{}`) has the same sha256 as an earlier key",
                    k.name
                )));
            }
            keys.push(ApiKey {
                name: k.name,
                role: k.role,
                digest,
            });
        }
        Ok(KeyRing { keys })
    }

    /// Reads and parses the key file at `path`.
    pub fn load(path: &Path) -> Result<KeyRing, KeyFileError> {
        let text = std::fs::read_to_string(path).map_err(|e| KeyFileError {
            path: path.display().to_string(),
            reason: format!("cannot read it: {e}"),
        })?;
        KeyRing::parse(&text, &path.display().to_string())
    }

    /// Number of keys.
    pub fn len(&self) -> usize {
        self.keys.len()
    }

    /// Whether there are no keys.
    pub fn is_empty(&self) -> bool {
        self.keys.is_empty()
    }

    /// The key whose digest is the SHA-256 of `presented`, compared in constant time against
    /// every stored digest (the scan never stops early).
    pub fn identify(&self, presented: &[u8]) -> Option<&ApiKey> {
        let mut digest = [0u8; 32];
        digest.copy_from_slice(&Sha256::digest(presented));
        let mut found = subtle::Choice::from(0);
        let mut index = 0u64;
        for (i, k) in self.keys.iter().enumerate() {
            let eq = k.digest[..].ct_eq(&digest[..]);
            index.conditional_assign(&(i as u64), eq);
            found |= eq;
        }
        if bool::from(found) {
            self.keys.get(usize::try_from(index).ok()?)
        } else {
            None
        }
    }
}

fn parse_hex_digest(s: &str) -> Option<[u8; 32]> {
    let bytes = s.as_bytes();
    if bytes.len() != 64 {
        return None;
    }
    let mut out = [0u8; 32];
    for (o, pair) in out.iter_mut().zip(bytes.chunks_exact(2)) {
        let hi = (pair[0] as char).to_digit(16)?;
        let lo = (pair[1] as char).to_digit(16)?;
        *o = u8::try_from(hi * 16 + lo).ok()?;
    }
    Some(out)
}

/// The name of the key that authenticated a request; set as a response extension so outer
/// layers (metrics) can label by key without seeing the key.
#[derive(Clone, Debug)]
pub struct KeyName(pub String);

/// The live access-control state: the current key ring (swapped on reload) and the per-key
/// in-flight limits.
#[derive(Debug)]
pub struct Auth {
    path: PathBuf,
    ring: RwLock<Arc<KeyRing>>,
    max_per_key: usize,
    in_flight: Mutex<HashMap<String, Arc<Semaphore>>>,
}

impl Auth {
    /// Loads the key file at `path`; each key may have `max_per_key` requests in flight.
    pub fn load(path: &Path, max_per_key: usize) -> Result<Auth, KeyFileError> {
        let ring = KeyRing::load(path)?;
        Ok(Auth {
            path: path.to_path_buf(),
            ring: RwLock::new(Arc::new(ring)),
            max_per_key,
            in_flight: Mutex::new(HashMap::new()),
        })
    }

    /// The key file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The current key ring.
    pub fn ring(&self) -> Arc<KeyRing> {
        Arc::clone(&self.ring.read().unwrap_or_else(|p| p.into_inner()))
    }

    /// Re-reads the key file; on error the previous keys stay in force. Returns the number of
    /// keys now accepted.
    pub fn reload(&self) -> Result<usize, KeyFileError> {
        let ring = KeyRing::load(&self.path)?;
        let n = ring.len();
        *self.ring.write().unwrap_or_else(|p| p.into_inner()) = Arc::new(ring);
        Ok(n)
    }

    /// A slot for one more request of key `name`, or `None` when it has
    /// `max_per_key` requests in flight.
    fn admit(&self, name: &str) -> Option<OwnedSemaphorePermit> {
        let sem = {
            let mut map = self.in_flight.lock().unwrap_or_else(|p| p.into_inner());
            Arc::clone(
                map.entry(name.to_string())
                    .or_insert_with(|| Arc::new(Semaphore::new(self.max_per_key))),
            )
        };
        sem.try_acquire_owned().ok()
    }
}

/// The bearer token of `Authorization: Bearer <token>` (scheme case-insensitive).
fn bearer(req: &Request) -> Result<&[u8], ApiError> {
    let value = req.headers().get(header::AUTHORIZATION).ok_or_else(|| {
        ApiError::Unauthorized("this route needs an `Authorization: Bearer <key>` header".into())
    })?;
    let bytes = value.as_bytes();
    let scheme_ok = bytes.len() > 7 && bytes[..7].eq_ignore_ascii_case(b"bearer ");
    if !scheme_ok {
        return Err(ApiError::Unauthorized(
            "the Authorization header must be `Bearer <key>`".into(),
        ));
    }
    Ok(bytes[7..].trim_ascii())
}

/// Middleware: lets public routes through, otherwise authenticates the bearer key, checks its
/// role against [`required_access`] and its in-flight limit. A service without a key file
/// (loopback or `--allow-unauthenticated`) lets everything through.
///
/// Its state is the service's access control alone (not the whole handler state), so this
/// module does not depend on `state` (which holds an [`Auth`]).
pub async fn authorize(
    State(auth): State<Option<Arc<Auth>>>,
    mut req: Request,
    next: Next,
) -> Response {
    let Some(auth) = auth.as_ref() else {
        return next.run(req).await;
    };
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|p| p.as_str().to_owned());
    let Access::Role(needed) = required_access(req.method(), route.as_deref()) else {
        return next.run(req).await;
    };
    let ring = auth.ring();
    let key = match bearer(&req) {
        Ok(token) => match ring.identify(token) {
            Some(key) => key.clone(),
            None => return ApiError::Unauthorized("unknown API key".into()).into_response(),
        },
        Err(e) => return e.into_response(),
    };
    tracing::Span::current().record("key", key.name.as_str());
    let mut response = if key.role < needed {
        ApiError::Forbidden(format!(
            "key `{}` has role `{}`; {} {} needs `{}`",
            key.name,
            key.role.as_str(),
            req.method(),
            route.as_deref().unwrap_or("this route"),
            needed.as_str()
        ))
        .into_response()
    } else if let Some(_permit) = auth.admit(&key.name) {
        req.extensions_mut().insert(seasonloc_app::caller::Caller {
            name: key.name.clone(),
            admin: key.role == Role::Admin,
        });
        next.run(req).await
    } else {
        ApiError::TooManyRequests(format!(
            "key `{}` already has {} requests in flight (the per-key limit)",
            key.name, auth.max_per_key
        ))
        .into_response()
    };
    response.extensions_mut().insert(KeyName(key.name));
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sha(key: &str) -> String {
        Sha256::digest(key.as_bytes())
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect()
    }

    fn ring() -> KeyRing {
        let text = serde_json::json!({"keys": [
            {"name": "ops", "role": "admin", "sha256": sha("adm-secret")},
            {"name": "car-7", "role": "vehicle", "sha256": sha("veh-secret").to_uppercase()},
            {"name": "wall", "role": "reader", "sha256": sha("rd-secret")},
        ]})
        .to_string();
        KeyRing::parse(&text, "keys.json").unwrap()
    }

    #[test]
    fn keys_are_identified_by_their_digest() {
        let r = ring();
        assert_eq!(r.len(), 3);
        assert_eq!(r.identify(b"adm-secret").unwrap().name, "ops");
        assert_eq!(r.identify(b"veh-secret").unwrap().role, Role::Vehicle);
        assert_eq!(r.identify(b"rd-secret").unwrap().role, Role::Reader);
        assert!(r.identify(b"adm-secre").is_none());
        assert!(r.identify(b"").is_none());
        assert!(r.identify(sha("adm-secret").as_bytes()).is_none());
    }

    #[test]
    fn bad_key_files_are_rejected_with_the_entry() {
        let bad = [
            (r#"{"keys": []}"#, "empty"),
            (
                r#"{"keys": [{"name": "a", "role": "root", "sha256": "00"}]}"#,
                "keys[0].role",
            ),
            (
                r#"{"keys": [{"name": "a", "role": "admin", "sha256": "abc"}]}"#,
                "64 hexadecimal",
            ),
            (
                r#"{"keys": [{"name": "", "role": "admin", "sha256": "abc"}]}"#,
                "keys[0].name",
            ),
            (r#"{"keys": [{"name": "a", "role": "admin"}]}"#, "sha256"),
            (r#"{"keys": [], "extra": 1}"#, "extra"),
            ("not json", "expected"),
        ];
        for (text, needle) in bad {
            let e = KeyRing::parse(text, "k.json").unwrap_err().to_string();
            assert!(e.contains(needle) && e.contains("k.json"), "{text}: {e}");
        }
        let d = sha("x");
        let twice = format!(
            r#"{{"keys": [{{"name": "a", "role": "admin", "sha256": "{d}"}},
                           {{"name": "a", "role": "reader", "sha256": "{}"}}]}}"#,
            sha("y")
        );
        assert!(KeyRing::parse(&twice, "k")
            .unwrap_err()
            .reason
            .contains("twice"));
        let same = format!(
            r#"{{"keys": [{{"name": "a", "role": "admin", "sha256": "{d}"}},
                           {{"name": "b", "role": "reader", "sha256": "{d}"}}]}}"#
        );
        assert!(KeyRing::parse(&same, "k")
            .unwrap_err()
            .reason
            .contains("same sha256"));
    }

    #[test]
    fn roles_follow_the_issue() {
        use Access::{Public, Role as R};
        let get = Method::GET;
        let post = Method::POST;
        let del = Method::DELETE;
        let cases: &[(&Method, Option<&str>, Access)] = &[
            (&get, Some("/healthz"), Public),
            (&get, Some("/readyz"), Public),
            (&get, Some("/"), Public),
            (&get, Some("/assets/{name}"), Public),
            (&get, Some("/trips/{id}"), Public),
            (&get, Some("/metrics"), R(Role::Reader)),
            (&get, Some("/v1/maps"), R(Role::Reader)),
            (&get, Some("/v1/trips/{id}"), R(Role::Reader)),
            (&get, None, R(Role::Reader)),
            (&post, Some("/v1/maps/{id}/localize"), R(Role::Vehicle)),
            (&post, Some("/v1/trips/{id}/close"), R(Role::Vehicle)),
            (&post, Some("/v1/maps"), R(Role::Admin)),
            (&post, Some("/v1/maps/{id}/images"), R(Role::Admin)),
            (&post, Some("/healthz"), R(Role::Admin)),
            (&del, Some("/v1/maps/{id}"), R(Role::Admin)),
            (&post, None, R(Role::Admin)),
        ];
        for (m, route, want) in cases {
            assert_eq!(required_access(m, *route), *want, "{m} {route:?}");
        }
        assert!(Role::Reader < Role::Vehicle && Role::Vehicle < Role::Admin);
    }

    #[test]
    fn a_failed_reload_keeps_the_old_keys() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("keys.json");
        let one = |name: &str, key: &str| {
            format!(
                r#"{{"keys": [{{"name": "{name}", "role": "admin", "sha256": "{}"}}]}}"#,
                sha(key)
            )
        };
        std::fs::write(&path, one("first", "k1")).unwrap();
        let auth = Auth::load(&path, 2).unwrap();
        assert!(auth.ring().identify(b"k1").is_some());
        std::fs::write(&path, "{ torn").unwrap();
        assert!(auth.reload().is_err());
        assert!(auth.ring().identify(b"k1").is_some());
        std::fs::write(&path, one("second", "k2")).unwrap();
        assert_eq!(auth.reload().unwrap(), 1);
        assert!(auth.ring().identify(b"k1").is_none());
        assert_eq!(auth.ring().identify(b"k2").unwrap().name, "second");
    }

    #[test]
    fn in_flight_requests_are_capped_per_key() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("keys.json");
        std::fs::write(
            &path,
            format!(
                r#"{{"keys": [{{"name": "a", "role": "admin", "sha256": "{}"}}]}}"#,
                sha("k")
            ),
        )
        .unwrap();
        let auth = Auth::load(&path, 2).unwrap();
        let p1 = auth.admit("a").unwrap();
        let _p2 = auth.admit("a").unwrap();
        assert!(auth.admit("a").is_none());
        assert!(auth.admit("b").is_some(), "another key has its own slots");
        drop(p1);
        assert!(auth.admit("a").is_some());
    }
}
