//! Configuration of `seasonloc serve`: a clap [`ServeArgs`] whose every field can also come
//! from an environment variable (`SEASONLOC_*`; command-line flags win), validated once into
//! [`Settings`].
//!
//! Invariant: every limit in [`Settings`] is non-zero, so the layers built from it never reject
//! everything; `.env.sample` and `docs/service.md` list the same keys as this file.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

/// Flags of `seasonloc serve` (each with an environment-variable equivalent).
#[derive(Clone, Debug, clap::Args)]
pub struct ServeArgs {
    /// TOML file of settings: the keys are these flags' names in snake_case
    /// (`max_body_bytes = 1048576`); environment variables and flags win over it, and an
    /// unknown key is refused with its name. Read by the binary's argument parser
    /// ([`crate::config_file`]).
    #[arg(long, env = "SEASONLOC_CONFIG")]
    pub config: Option<PathBuf>,
    /// Log format: `text` (human-readable) or `json` (one object per line, for Loki or
    /// Elasticsearch). Default: `text` when stderr is a terminal, `json` otherwise.
    #[arg(long, env = "SEASONLOC_LOG_FORMAT", value_enum)]
    pub log_format: Option<LogFormat>,
    /// OpenTelemetry collector to send traces to over OTLP/HTTP (JSON), as a base URL such as
    /// `http://otel-collector:4318` (spans go to its `/v1/traces`). None: no traces.
    #[arg(long, env = "OTEL_EXPORTER_OTLP_ENDPOINT")]
    pub otlp_endpoint: Option<String>,
    /// Address to listen on (`HOST:PORT`; port 0 picks a free port).
    #[arg(long, env = "SEASONLOC_ADDR", default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Folder of the embedded store (created when missing; unused with `--database-url`).
    #[arg(long, env = "SEASONLOC_DATA_DIR", default_value = "./seasonloc-data")]
    pub data_dir: PathBuf,
    /// PostgreSQL database holding all state instead of the embedded store
    /// (`postgres://user:password@host:port/database`); any number of replicas may serve one
    /// database. Its schema is created or upgraded at start-up.
    #[arg(long, env = "SEASONLOC_DATABASE_URL", hide_env_values = true)]
    pub database_url: Option<String>,
    /// Page cache of the embedded store in bytes (sled keeps this much of the store in memory;
    /// unused with `--database-url`).
    #[arg(long, env = "SEASONLOC_STORE_CACHE_BYTES", default_value_t = 128 * 1024 * 1024)]
    pub store_cache_bytes: u64,
    /// Statement timeout on PostgreSQL, in seconds: the database cancels a longer statement,
    /// and a store call without an answer one second later (a hung database) answers 503
    /// `not_ready`.
    #[arg(
        long,
        env = "SEASONLOC_DATABASE_STATEMENT_TIMEOUT_SECS",
        default_value_t = 5
    )]
    pub database_statement_timeout_secs: u64,
    /// TCP user timeout of PostgreSQL connections, in seconds: a connection whose sent data
    /// stays unacknowledged this long (or whose keepalive probes go unanswered) is closed.
    #[arg(
        long,
        env = "SEASONLOC_DATABASE_TCP_USER_TIMEOUT_SECS",
        default_value_t = 10
    )]
    pub database_tcp_user_timeout_secs: u64,
    /// Largest accepted request body in bytes (uploads included); larger bodies get 413.
    #[arg(long, env = "SEASONLOC_MAX_BODY_BYTES", default_value_t = 64 * 1024 * 1024)]
    pub max_body_bytes: usize,
    /// Most images (or descriptors) accepted in one batch.
    #[arg(long, env = "SEASONLOC_MAX_BATCH_IMAGES", default_value_t = 4096)]
    pub max_batch_images: usize,
    /// Largest accepted image in pixels (width x height), checked before decoding.
    #[arg(long, env = "SEASONLOC_MAX_IMAGE_PIXELS", default_value_t = 16_000_000)]
    pub max_image_pixels: u64,
    /// Most decoded pixels of a batch that is held decoded as a whole (a co-occurrence map's
    /// first batch or a drive: the sum of the images' width x height, checked from their
    /// headers before decoding); larger batches get 400 `batch_too_large`. Other batches are
    /// decoded one image per CPU-pool thread at a time and need no such budget.
    #[arg(long, env = "SEASONLOC_MAX_BATCH_PIXELS", default_value_t = 1 << 28)]
    pub max_batch_pixels: u64,
    /// Seconds after which a request is abandoned with 503 `timeout`.
    #[arg(long, env = "SEASONLOC_REQUEST_TIMEOUT_SECS", default_value_t = 120)]
    pub request_timeout_secs: u64,
    /// Requests handled at once; further requests are shed with 503 `overloaded`.
    #[arg(long, env = "SEASONLOC_MAX_CONCURRENT_REQUESTS", default_value_t = 256)]
    pub max_concurrent_requests: usize,
    /// Localize requests admitted at once (running or waiting for a CPU); beyond that the
    /// service answers 503 `queue_full` with `Retry-After`.
    #[arg(long, env = "SEASONLOC_LOCALIZE_QUEUE", default_value_t = 16)]
    pub localize_queue: usize,
    /// Longest a localize request waits for a CPU, first come first served; a request that
    /// would wait longer (estimated from recent localizations) is refused at once with 503
    /// `queue_full` and `Retry-After`, so an admitted request never runs into the request
    /// timeout by waiting. Must be below `--request-timeout-secs`.
    #[arg(long, env = "SEASONLOC_LOCALIZE_MAX_WAIT_SECS", default_value_t = 30)]
    pub localize_max_wait_secs: u64,
    /// Seconds a client has to send a request's complete header once the connection is open
    /// (or idle between requests); slower connections are closed (slowloris).
    #[arg(long, env = "SEASONLOC_HEADER_READ_TIMEOUT_SECS", default_value_t = 10)]
    pub header_read_timeout_secs: u64,
    /// Seconds a request body may stall (no bytes arriving) before the request fails with 408
    /// `body_timeout`; the whole request stays under `--request-timeout-secs`.
    #[arg(long, env = "SEASONLOC_BODY_READ_TIMEOUT_SECS", default_value_t = 20)]
    pub body_read_timeout_secs: u64,
    /// Seconds a client has to send a request's whole body, from the end of its header;
    /// a body still arriving then (however steadily it trickles) fails with 408
    /// `body_timeout`. Values above `--request-timeout-secs` mean that timeout.
    #[arg(long, env = "SEASONLOC_BODY_DEADLINE_SECS", default_value_t = 45)]
    pub body_deadline_secs: u64,
    /// Connections served at once (0 = as many as the process's file-descriptor limit allows,
    /// less a reserve for the store and the pool). At the cap, a new connection closes the
    /// connection that has waited longest for a request header (an idle or half-sent one);
    /// when every connection is busy, the new one is closed.
    #[arg(long, env = "SEASONLOC_MAX_CONNECTIONS", default_value_t = 0)]
    pub max_connections: usize,
    /// Threads of the CPU pool for decoding, extraction and solving (0 = one per core; at most
    /// 1024).
    #[arg(long, env = "SEASONLOC_WORKER_THREADS", default_value_t = 0)]
    pub worker_threads: usize,
    /// Seconds to let in-flight requests finish after SIGTERM/Ctrl-C before exiting anyway.
    #[arg(long, env = "SEASONLOC_SHUTDOWN_TIMEOUT_SECS", default_value_t = 30)]
    pub shutdown_timeout_secs: u64,
    /// ONNX model used by CNN maps whose descriptor names no `model` (optional; checked when
    /// such a map is created).
    #[arg(long, env = "SEASONLOC_CNN_MODEL")]
    pub cnn_model: Option<PathBuf>,
    /// Longest descriptor (in f32 values) an image may give or a map may have; bounds the
    /// memory of a request in advance (batch x 4 bytes x this). Larger images get 422
    /// `descriptor_length` before they are decoded.
    #[arg(long, env = "SEASONLOC_MAX_DESCRIPTOR_LEN", default_value_t = 1 << 20)]
    pub max_descriptor_len: usize,
    /// Directory CNN models may be read from: a create request's `model` must name a regular
    /// file inside it (none: requests cannot name a model, only `--cnn-model` is used).
    #[arg(long, env = "SEASONLOC_MODEL_DIR")]
    pub model_dir: Option<PathBuf>,
    /// Largest accepted CNN model file in bytes.
    #[arg(long, env = "SEASONLOC_MAX_MODEL_BYTES", default_value_t = 256 * 1024 * 1024)]
    pub max_model_bytes: u64,
    /// JSON file of API keys (`{"keys": [{"name", "role", "sha256"}]}`); when set, every route
    /// but the probes and the dashboard's pages needs `Authorization: Bearer <key>`. Re-read
    /// on SIGHUP.
    #[arg(long, env = "SEASONLOC_API_KEYS")]
    pub api_keys: Option<PathBuf>,
    /// Serve without access control on a non-loopback address (explicit opt-out; without it,
    /// `serve` on such an address refuses to start unless `--api-keys` is given).
    #[arg(long, env = "SEASONLOC_ALLOW_UNAUTHENTICATED")]
    pub allow_unauthenticated: bool,
    /// Requests one API key may have in flight; more get 429 `too_many_requests`.
    #[arg(long, env = "SEASONLOC_MAX_REQUESTS_PER_KEY", default_value_t = 32)]
    pub max_requests_per_key: usize,
    /// Origin allowed to call the API from a browser page (CORS), e.g.
    /// `https://ops.example.com`; repeatable (comma-separated in the environment). None: no
    /// cross-origin access.
    #[arg(
        long = "cors-origin",
        env = "SEASONLOC_CORS_ORIGINS",
        value_delimiter = ','
    )]
    pub cors_origins: Vec<String>,
    /// Accepted values of the `Host` header (host name, or `host:port`), against DNS
    /// rebinding; repeatable (comma-separated in the environment); `*` accepts any host.
    /// None: any host with `--api-keys`; without keys, only `localhost` and IP addresses (a
    /// rebinding page's name is neither).
    #[arg(
        long = "allowed-host",
        env = "SEASONLOC_ALLOWED_HOSTS",
        value_delimiter = ','
    )]
    pub allowed_hosts: Vec<String>,
}

impl Default for ServeArgs {
    fn default() -> Self {
        ServeArgs {
            config: None,
            log_format: None,
            otlp_endpoint: None,
            addr: SocketAddr::from(([127, 0, 0, 1], 8080)),
            data_dir: PathBuf::from("./seasonloc-data"),
            database_url: None,
            store_cache_bytes: 128 * 1024 * 1024,
            database_statement_timeout_secs: 5,
            database_tcp_user_timeout_secs: 10,
            max_body_bytes: 64 * 1024 * 1024,
            max_batch_images: 4096,
            max_image_pixels: 16_000_000,
            max_batch_pixels: 1 << 28,
            request_timeout_secs: 120,
            max_concurrent_requests: 256,
            localize_queue: 16,
            localize_max_wait_secs: 30,
            header_read_timeout_secs: 10,
            body_read_timeout_secs: 20,
            body_deadline_secs: 45,
            max_connections: 0,
            worker_threads: 0,
            shutdown_timeout_secs: 30,
            cnn_model: None,
            max_descriptor_len: 1 << 20,
            model_dir: None,
            max_model_bytes: 256 * 1024 * 1024,
            api_keys: None,
            allow_unauthenticated: false,
            max_requests_per_key: 32,
            cors_origins: Vec::new(),
            allowed_hosts: Vec::new(),
        }
    }
}

/// How log lines are written (`--log-format`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// `tracing`'s human-readable lines.
    Text,
    /// One JSON object per line.
    Json,
}

/// Validated service settings (see [`ServeArgs`] for the meaning of each field).
#[derive(Clone, Debug, PartialEq)]
pub struct Settings {
    /// Listen address.
    pub addr: SocketAddr,
    /// Store folder (the embedded engine).
    pub data_dir: PathBuf,
    /// The shared PostgreSQL database, when set (instead of `data_dir`).
    pub database_url: Option<DatabaseUrl>,
    /// The embedded store's page cache in bytes, > 0.
    pub store_cache_bytes: u64,
    /// PostgreSQL's statement timeout (and, plus a second, a store call's bound), > 0.
    pub database_statement_timeout: Duration,
    /// PostgreSQL connections' TCP user timeout, > 0.
    pub database_tcp_user_timeout: Duration,
    /// Body limit in bytes, > 0.
    pub max_body_bytes: usize,
    /// Batch limit, > 0.
    pub max_batch_images: usize,
    /// Pixel limit per image, > 0.
    pub max_image_pixels: u64,
    /// Decoded-pixel budget of a batch held whole, > 0.
    pub max_batch_pixels: u64,
    /// Per-request timeout, > 0.
    pub request_timeout: Duration,
    /// Concurrency limit, > 0.
    pub max_concurrent_requests: usize,
    /// Localize admission limit, > 0.
    pub localize_queue: usize,
    /// Longest wait of an admitted localize request for its turn, > 0 and < `request_timeout`.
    pub localize_max_wait: Duration,
    /// Time to receive a request's header, > 0.
    pub header_read_timeout: Duration,
    /// Longest stall of a request body, > 0.
    pub body_read_timeout: Duration,
    /// Longest time to receive a whole request body, > 0 and at most `request_timeout`.
    pub body_deadline: Duration,
    /// Connections served at once, > 0 (resolved from 0 = the descriptor limit's room).
    pub max_connections: usize,
    /// CPU pool threads, > 0 (resolved from 0 = one per core).
    pub worker_threads: usize,
    /// Drain time on shutdown.
    pub shutdown_timeout: Duration,
    /// Model of CNN maps created without a `model`.
    pub default_cnn_model: Option<PathBuf>,
    /// Descriptor length cap, > 0.
    pub max_descriptor_len: usize,
    /// Directory of model files requests may name.
    pub model_dir: Option<PathBuf>,
    /// Model file size cap, > 0.
    pub max_model_bytes: u64,
    /// API key file; `None` serves without access control (loopback or explicit opt-out).
    pub api_keys: Option<PathBuf>,
    /// In-flight requests per key, > 0.
    pub max_requests_per_key: usize,
    /// Origins allowed by CORS (exact `scheme://host[:port]` strings).
    pub cors_origins: Vec<String>,
    /// Which `Host` header values are answered.
    pub hosts: HostPolicy,
}

/// Which `Host` header values the service answers (DNS rebinding: a hostile page on a name
/// that resolves to this server would otherwise be same-origin with it). The probes are
/// answered under any name.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum HostPolicy {
    /// Any `Host` (`--allowed-host '*'`, or the default with API keys: a rebinding page has no
    /// key).
    Any,
    /// Only these names (lowercase, each a host name or `host:port`), and IP addresses when
    /// `ip_literals` (the default without keys: `localhost` and IP addresses, which no
    /// rebinding page can be served under).
    Only {
        /// Accepted names.
        names: Vec<String>,
        /// Whether any IP address (`127.0.0.1`, `[::1]`, ...) is accepted too.
        ip_literals: bool,
    },
}

/// The names a keyless service answers by default, besides IP addresses.
pub const LOOPBACK_NAMES: &[&str] = &["localhost"];

impl HostPolicy {
    /// Whether a request with this `Host` header value (`None`: no header) is answered.
    pub fn allows(&self, host: Option<&str>) -> bool {
        let (names, ip_literals) = match self {
            HostPolicy::Any => return true,
            HostPolicy::Only { names, ip_literals } => (names, *ip_literals),
        };
        let Some(h) = host.map(str::to_ascii_lowercase) else {
            return false;
        };
        let name = match h.rsplit_once(':') {
            // `[::1]:8080` and `host:8080`; a bare IPv6 literal keeps its brackets.
            Some((name, port)) if !port.is_empty() && port.bytes().all(|b| b.is_ascii_digit()) => {
                name
            }
            _ => h.as_str(),
        };
        if names.iter().any(|a| *a == h || a == name) {
            return true;
        }
        ip_literals
            && (name.parse::<std::net::Ipv4Addr>().is_ok()
                || name
                    .strip_prefix('[')
                    .and_then(|n| n.strip_suffix(']'))
                    .is_some_and(|n| n.parse::<std::net::Ipv6Addr>().is_ok()))
    }
}

/// Descriptors kept out of `--max-connections`' automatic value: the store's files, the
/// PostgreSQL pool, the runtime, logs and the accept of one connection past the cap.
pub const RESERVED_DESCRIPTORS: usize = 128;

/// The process's soft `RLIMIT_NOFILE` as `/proc/self/limits` shows it: `None` where it cannot
/// be read, `Some(None)` when it is `unlimited`.
pub fn open_files_soft_limit() -> Option<Option<u64>> {
    let text = std::fs::read_to_string("/proc/self/limits").ok()?;
    let value = text
        .lines()
        .find(|l| l.starts_with("Max open files"))
        .and_then(|l| l.split_whitespace().nth(3))?
        .to_string();
    Some(value.parse::<u64>().ok())
}

/// Connections the process's descriptor limit leaves room for (its soft `RLIMIT_NOFILE`,
/// [`open_files_soft_limit`], less [`RESERVED_DESCRIPTORS`]; 1024 assumed where it cannot be
/// read), at least 16.
pub fn descriptor_room() -> usize {
    let soft = match open_files_soft_limit() {
        None => 1024,
        Some(None) => usize::MAX / 2,
        Some(Some(n)) => usize::try_from(n).unwrap_or(usize::MAX / 2),
    };
    soft.saturating_sub(RESERVED_DESCRIPTORS).max(16)
}

/// A database URL. It may carry a password, so it is never printed: `Debug` shows `***`.
#[derive(Clone, PartialEq, Eq)]
pub struct DatabaseUrl(pub String);

impl std::fmt::Debug for DatabaseUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("DatabaseUrl(***)")
    }
}

/// Largest `--worker-threads`.
pub const MAX_WORKER_THREADS: usize = 1024;

/// A configuration value that cannot work.
#[derive(Debug, thiserror::Error)]
#[error("invalid setting `{name}`: {reason}")]
pub struct ConfigError {
    /// The flag name without dashes, e.g. `max_body_bytes`.
    pub name: &'static str,
    /// Why it was rejected.
    pub reason: String,
}

impl ServeArgs {
    /// Checks every limit and resolves defaults into [`Settings`].
    pub fn validate(&self) -> Result<Settings, ConfigError> {
        fn positive(name: &'static str, v: u64) -> Result<(), ConfigError> {
            if v == 0 {
                return Err(ConfigError {
                    name,
                    reason: "must be greater than 0".into(),
                });
            }
            Ok(())
        }
        positive("max_body_bytes", self.max_body_bytes as u64)?;
        positive("max_batch_images", self.max_batch_images as u64)?;
        positive("max_image_pixels", self.max_image_pixels)?;
        positive("request_timeout_secs", self.request_timeout_secs)?;
        positive(
            "max_concurrent_requests",
            self.max_concurrent_requests as u64,
        )?;
        positive("localize_queue", self.localize_queue as u64)?;
        positive("localize_max_wait_secs", self.localize_max_wait_secs)?;
        positive("header_read_timeout_secs", self.header_read_timeout_secs)?;
        positive("body_read_timeout_secs", self.body_read_timeout_secs)?;
        positive("body_deadline_secs", self.body_deadline_secs)?;
        positive("max_batch_pixels", self.max_batch_pixels)?;
        positive("store_cache_bytes", self.store_cache_bytes)?;
        positive(
            "database_statement_timeout_secs",
            self.database_statement_timeout_secs,
        )?;
        positive(
            "database_tcp_user_timeout_secs",
            self.database_tcp_user_timeout_secs,
        )?;
        if self.localize_max_wait_secs >= self.request_timeout_secs {
            return Err(ConfigError {
                name: "localize_max_wait_secs",
                reason: format!(
                    "must be below request_timeout_secs ({}), got {}: a request that waits \
                     that long would time out after being admitted",
                    self.request_timeout_secs, self.localize_max_wait_secs
                ),
            });
        }
        positive("max_requests_per_key", self.max_requests_per_key as u64)?;
        positive("max_model_bytes", self.max_model_bytes)?;
        positive("max_descriptor_len", self.max_descriptor_len as u64)?;
        // An empty value (e.g. `SEASONLOC_API_KEYS=` in `.env`) means "no key file".
        let api_keys = self.api_keys.clone().filter(|p| !p.as_os_str().is_empty());
        if api_keys.is_none() && !self.allow_unauthenticated && !self.addr.ip().is_loopback() {
            return Err(ConfigError {
                name: "api_keys",
                reason: format!(
                    "refusing to serve on {} (not a loopback address) without access control: \
                     pass --api-keys FILE (SEASONLOC_API_KEYS), or --allow-unauthenticated to \
                     serve anyone who can reach the port",
                    self.addr
                ),
            });
        }
        let cors_origins: Vec<String> = self
            .cors_origins
            .iter()
            .map(|o| o.trim().trim_end_matches('/').to_string())
            .filter(|o| !o.is_empty())
            .collect();
        for o in &cors_origins {
            let valid = (o.starts_with("http://") || o.starts_with("https://"))
                && !o.contains(char::is_whitespace)
                && axum::http::HeaderValue::from_str(o).is_ok()
                && o.split("://")
                    .nth(1)
                    .is_some_and(|h| !h.is_empty() && !h.contains('/'));
            if !valid {
                return Err(ConfigError {
                    name: "cors_origin",
                    reason: format!("`{o}` is not an origin like https://host[:port]"),
                });
            }
        }
        let allowed_hosts: Vec<String> = self
            .allowed_hosts
            .iter()
            .map(|h| h.trim().to_ascii_lowercase())
            .filter(|h| !h.is_empty())
            .collect();
        let hosts = if allowed_hosts.iter().any(|h| h == "*") {
            HostPolicy::Any
        } else if !allowed_hosts.is_empty() {
            HostPolicy::Only {
                names: allowed_hosts,
                ip_literals: false,
            }
        } else if api_keys.is_some() {
            HostPolicy::Any
        } else {
            HostPolicy::Only {
                names: LOOPBACK_NAMES.iter().map(|n| n.to_string()).collect(),
                ip_literals: true,
            }
        };
        let max_connections = if self.max_connections == 0 {
            descriptor_room()
        } else {
            self.max_connections
        };
        if self.data_dir.as_os_str().is_empty() {
            return Err(ConfigError {
                name: "data_dir",
                reason: "must not be empty".into(),
            });
        }
        // Far above any machine's cores: a typo such as 100000 would otherwise start that many
        // threads (and their stacks) before the server says a word.
        if self.worker_threads > MAX_WORKER_THREADS {
            return Err(ConfigError {
                name: "worker_threads",
                reason: format!(
                    "must be at most {MAX_WORKER_THREADS} (0 = one per core), got {}",
                    self.worker_threads
                ),
            });
        }
        let worker_threads = if self.worker_threads == 0 {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        } else {
            self.worker_threads
        };
        // An empty value (e.g. `SEASONLOC_DATABASE_URL=` in `.env`) means "the embedded store".
        let database_url = match self.database_url.as_deref().map(str::trim) {
            None | Some("") => None,
            Some(url) if url.starts_with("postgres://") || url.starts_with("postgresql://") => {
                // `user:pa@ss@host` is ambiguous: the driver would take `ss@host` for the host
                // and every error would print that piece of the password.
                let authority = url.split_once("://").map_or("", |(_, rest)| rest);
                let authority = authority.split(['/', '?']).next().unwrap_or("");
                if authority.matches('@').count() > 1 {
                    return Err(ConfigError {
                        name: "database_url",
                        reason: "has more than one `@` before the host: write an `@` in the \
                                 user name or password as %40"
                            .into(),
                    });
                }
                Some(DatabaseUrl(url.to_string()))
            }
            Some(_) => {
                return Err(ConfigError {
                    name: "database_url",
                    reason: "must start with postgres:// or postgresql://".into(),
                })
            }
        };
        Ok(Settings {
            addr: self.addr,
            data_dir: self.data_dir.clone(),
            database_url,
            store_cache_bytes: self.store_cache_bytes,
            database_statement_timeout: Duration::from_secs(self.database_statement_timeout_secs),
            database_tcp_user_timeout: Duration::from_secs(self.database_tcp_user_timeout_secs),
            max_body_bytes: self.max_body_bytes,
            max_batch_images: self.max_batch_images,
            max_image_pixels: self.max_image_pixels,
            max_batch_pixels: self.max_batch_pixels,
            request_timeout: Duration::from_secs(self.request_timeout_secs),
            max_concurrent_requests: self.max_concurrent_requests,
            localize_queue: self.localize_queue,
            localize_max_wait: Duration::from_secs(self.localize_max_wait_secs),
            header_read_timeout: Duration::from_secs(self.header_read_timeout_secs),
            body_read_timeout: Duration::from_secs(self.body_read_timeout_secs),
            // The request timeout bounds the whole request, its body included.
            body_deadline: Duration::from_secs(
                self.body_deadline_secs.min(self.request_timeout_secs),
            ),
            max_connections,
            worker_threads,
            shutdown_timeout: Duration::from_secs(self.shutdown_timeout_secs),
            // An empty value (e.g. `SEASONLOC_CNN_MODEL=` in `.env`) means "no default model".
            default_cnn_model: self.cnn_model.clone().filter(|p| !p.as_os_str().is_empty()),
            max_descriptor_len: self.max_descriptor_len,
            model_dir: self.model_dir.clone().filter(|p| !p.as_os_str().is_empty()),
            max_model_bytes: self.max_model_bytes,
            api_keys,
            max_requests_per_key: self.max_requests_per_key,
            cors_origins,
            hosts,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        serve: ServeArgs,
    }

    #[test]
    fn defaults_match_the_spec() {
        let cli = Cli::try_parse_from(["seasonloc"]).unwrap();
        let s = cli.serve.validate().unwrap();
        // The environment of the test runner could set these; the spec's defaults apply
        // only when it does not.
        if std::env::var_os("SEASONLOC_ADDR").is_none() {
            assert_eq!(s.addr.to_string(), "127.0.0.1:8080");
        }
        if std::env::var_os("SEASONLOC_DATA_DIR").is_none() {
            assert_eq!(s.data_dir, PathBuf::from("./seasonloc-data"));
        }
        assert!(s.worker_threads >= 1);
        assert_eq!(ServeArgs::default().addr, cli.serve.addr);
        if std::env::var_os("SEASONLOC_STORE_CACHE_BYTES").is_none() {
            assert_eq!(
                s.store_cache_bytes,
                seasonloc_store::sled::DEFAULT_CACHE_BYTES
            );
        }
        if std::env::var_os("SEASONLOC_DATABASE_STATEMENT_TIMEOUT_SECS").is_none() {
            assert_eq!(
                s.database_statement_timeout,
                seasonloc_store::PgOptions::default().statement_timeout
            );
        }
        if std::env::var_os("SEASONLOC_DATABASE_TCP_USER_TIMEOUT_SECS").is_none() {
            assert_eq!(
                s.database_tcp_user_timeout,
                seasonloc_store::PgOptions::default().tcp_user_timeout
            );
        }
    }

    /// The store's cache and the database's timeouts come from flags, and none may be 0.
    #[test]
    fn store_flags_are_parsed_and_zero_is_refused() {
        let cli = Cli::try_parse_from([
            "seasonloc",
            "--store-cache-bytes",
            "1048576",
            "--database-statement-timeout-secs",
            "3",
            "--database-tcp-user-timeout-secs",
            "7",
        ])
        .unwrap();
        let s = cli.serve.validate().unwrap();
        assert_eq!(s.store_cache_bytes, 1 << 20);
        assert_eq!(s.database_statement_timeout, Duration::from_secs(3));
        assert_eq!(s.database_tcp_user_timeout, Duration::from_secs(7));
        for flag in [
            "--store-cache-bytes",
            "--database-statement-timeout-secs",
            "--database-tcp-user-timeout-secs",
        ] {
            let cli = Cli::try_parse_from(["seasonloc", flag, "0"]).unwrap();
            assert!(cli.serve.validate().is_err(), "{flag} 0 was accepted");
        }
    }

    #[test]
    fn flags_are_parsed() {
        let cli = Cli::try_parse_from([
            "seasonloc",
            "--addr",
            "0.0.0.0:9000",
            "--data-dir",
            "/tmp/x",
            "--max-batch-images",
            "7",
            "--allow-unauthenticated",
        ])
        .unwrap();
        let s = cli.serve.validate().unwrap();
        assert_eq!(s.addr.port(), 9000);
        assert_eq!(s.data_dir, PathBuf::from("/tmp/x"));
        assert_eq!(s.max_batch_images, 7);
    }

    #[test]
    fn env_sample_lists_every_setting() {
        use clap::CommandFactory;
        let mut from_flags: Vec<String> = Cli::command()
            .get_arguments()
            .filter_map(|a| a.get_env().map(|e| e.to_string_lossy().into_owned()))
            .collect();
        from_flags.push("RUST_LOG".into());
        from_flags.sort();
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../.env.sample");
        let text = std::fs::read_to_string(path).unwrap();
        let mut from_file: Vec<String> = text
            .lines()
            .filter(|l| !l.starts_with('#') && l.contains('='))
            .map(|l| l.split('=').next().unwrap().to_string())
            .collect();
        from_file.sort();
        assert_eq!(from_file, from_flags);
    }

    #[test]
    fn public_addresses_need_keys_or_an_explicit_opt_out() {
        let public = ServeArgs {
            addr: SocketAddr::from(([0, 0, 0, 0], 8080)),
            ..ServeArgs::default()
        };
        let err = public.validate().unwrap_err().to_string();
        assert!(
            err.contains("--api-keys") && err.contains("--allow-unauthenticated"),
            "{err}"
        );
        assert!(!err.contains('\n'), "one line: {err}");
        let keyed = ServeArgs {
            api_keys: Some(PathBuf::from("/run/secrets/keys.json")),
            ..public.clone()
        };
        assert!(keyed.validate().is_ok());
        let opted_out = ServeArgs {
            allow_unauthenticated: true,
            ..public.clone()
        };
        assert!(opted_out.validate().unwrap().api_keys.is_none());
        let v6_loopback = ServeArgs {
            addr: "[::1]:8080".parse().unwrap(),
            ..ServeArgs::default()
        };
        assert!(v6_loopback.validate().is_ok());
    }

    #[test]
    fn cors_origins_are_checked() {
        let ok = ServeArgs {
            cors_origins: vec![
                "https://ops.example.com/".into(),
                "http://localhost:3000".into(),
            ],
            ..ServeArgs::default()
        };
        assert_eq!(
            ok.validate().unwrap().cors_origins,
            vec!["https://ops.example.com", "http://localhost:3000"]
        );
        for bad in ["ops.example.com", "https://a.com/path", "https://"] {
            let args = ServeArgs {
                cors_origins: vec![bad.into()],
                ..ServeArgs::default()
            };
            assert_eq!(args.validate().unwrap_err().name, "cors_origin", "{bad}");
        }
    }

    #[test]
    fn database_urls_are_checked_and_never_printed() {
        let with = |url: &str| ServeArgs {
            database_url: Some(url.into()),
            ..ServeArgs::default()
        };
        let s = with("postgres://u:secret@db:5432/x").validate().unwrap();
        assert!(s.database_url.is_some());
        assert!(!format!("{s:?}").contains("secret"));
        assert_eq!(with("").validate().unwrap().database_url, None);
        assert_eq!(
            with("mysql://x").validate().unwrap_err().name,
            "database_url"
        );
        // An unencoded `@` in the password is refused without echoing any of it.
        let err = with("postgres://alice:Top@SECRET@127.0.0.1:1/db")
            .validate()
            .unwrap_err();
        assert_eq!(err.name, "database_url");
        assert!(!err.to_string().contains("SECRET"), "{err}");
        assert!(err.to_string().contains("%40"), "{err}");
        assert!(with("postgres://alice:Top%40SECRET@127.0.0.1:1/db")
            .validate()
            .is_ok());
    }

    #[test]
    fn zero_limits_are_rejected_by_name() {
        let args = ServeArgs {
            localize_queue: 0,
            ..ServeArgs::default()
        };
        let err = args.validate().unwrap_err();
        assert_eq!(err.name, "localize_queue");
        assert!(err.to_string().contains("localize_queue"));
    }

    #[test]
    fn keyless_services_answer_only_loopback_names_and_addresses_by_default() {
        let keyless = ServeArgs::default().validate().unwrap().hosts;
        for ok in [
            "127.0.0.1:8080",
            "localhost:8080",
            "LOCALHOST",
            "[::1]:8080",
            "[::1]",
        ] {
            assert!(keyless.allows(Some(ok)), "{ok}");
        }
        for bad in [
            "attacker-rebind.example",
            "attacker-rebind.example:8080",
            "localhost.evil.example",
            "127.0.0.1.evil.example",
            "",
        ] {
            assert!(!keyless.allows(Some(bad)), "{bad}");
        }
        assert!(!keyless.allows(None));
        let keyed = ServeArgs {
            api_keys: Some(PathBuf::from("/run/keys.json")),
            ..ServeArgs::default()
        };
        assert_eq!(keyed.validate().unwrap().hosts, HostPolicy::Any);
        let listed = ServeArgs {
            allowed_hosts: vec!["Seasonloc.Internal".into()],
            ..ServeArgs::default()
        };
        let listed = listed.validate().unwrap().hosts;
        assert!(listed.allows(Some("seasonloc.internal:8080")));
        assert!(!listed.allows(Some("127.0.0.1:8080")));
        let any = ServeArgs {
            allowed_hosts: vec!["*".into()],
            ..ServeArgs::default()
        };
        assert!(any
            .validate()
            .unwrap()
            .hosts
            .allows(Some("anything.example")));
    }

    #[test]
    fn the_body_deadline_is_within_the_request_timeout() {
        let args = ServeArgs {
            body_deadline_secs: 200,
            ..ServeArgs::default()
        };
        assert_eq!(
            args.validate().unwrap().body_deadline,
            Duration::from_secs(120)
        );
        let zero = ServeArgs {
            body_deadline_secs: 0,
            ..ServeArgs::default()
        };
        assert_eq!(zero.validate().unwrap_err().name, "body_deadline_secs");
        let s = ServeArgs::default().validate().unwrap();
        assert_eq!(s.body_deadline, Duration::from_secs(45));
        assert!(s.max_connections >= 16);
    }

    #[test]
    fn worker_threads_are_bounded() {
        let with = |n| ServeArgs {
            worker_threads: n,
            ..ServeArgs::default()
        };
        let err = with(100_000).validate().unwrap_err();
        assert_eq!(err.name, "worker_threads");
        assert!(err.to_string().contains("at most 1024"), "{err}");
        assert_eq!(
            with(MAX_WORKER_THREADS).validate().unwrap().worker_threads,
            1024
        );
        assert!(with(0).validate().unwrap().worker_threads >= 1);
    }
}
