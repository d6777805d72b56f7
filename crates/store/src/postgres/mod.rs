//! The shared engine: every record in one PostgreSQL database, so any number of stateless
//! replicas of the service can serve the same data (`seasonloc serve --database-url`).
//!
//! Only this module knows PostgreSQL. It owns the schema (the SQL files in
//! `migrations/postgres/`, applied in order at start-up by [`migrate`]) and keeps the write
//! rules of [`seasonloc_app::store`] with the database's own tools:
//!
//! * every change that spans several rows (a batch of images and the map's `image_count`, a
//!   trip batch's record, state and estimates) is one transaction; a map's children reference
//!   it `ON DELETE CASCADE`, so deleting a map is one statement;
//! * a commit returns only when it is durable (`synchronous_commit` is the server's default),
//!   so whatever the API acknowledged survives the loss of any replica;
//! * read-modify-write cycles lock the row they depend on (`SELECT ... FOR UPDATE` on the
//!   map for appends) or are one conditional `UPDATE` (a trip batch applies only `WHERE
//!   frame_count = expected`), so two replicas can never both apply a batch computed from one
//!   state;
//! * a failure to reach the database (refused or dropped connection, pool wait over, server
//!   shutting down) is [`StoreError::Unavailable`] (the API answers 503), and the pool drops
//!   broken connections and opens new ones, so a replica recovers by itself when the database
//!   comes back.
//!
//! Descriptors are stored compactly: one row per appended batch with the rows as raw
//! little-endian `f32` (`postgres/maps.rs`); a replica reads them once per map version into its cache
//! (`crate::app`), which checks the map's `image_count` first and reads only the new rows.
//!
//! `seasonloc_test_support::postgres` starts throw-away PostgreSQL servers for the test suites.

mod maps;
pub mod migrate;
mod records;
mod tls;

use crate::OrStore;
use std::ops::Range;
use std::time::Duration;

use async_trait::async_trait;
use deadpool_postgres::{Manager, ManagerConfig, Pool, PoolError, RecyclingMethod, Runtime};
use tokio_postgres::error::SqlState;

use seasonloc_app::model::{ImageMeta, LocalizationRecord, MapRecord, TripRecord};
use seasonloc_app::store::{
    now_ms, CoocWrite, IdempotencyRecord, ImageBatch, NewLocalization, NewMap, NewTrip, Page,
    PageRequest, Store, StoreError, StoreResult, TripBatch, TripState,
};
use seasonloc_core::trip::FrameEstimate;
use seasonloc_core::Matrix;

/// How long a request waits for a pooled connection, and a new connection to be made, before
/// the store answers [`StoreError::Unavailable`].
const CONNECT_TIMEOUT: Duration = Duration::from_secs(3);

/// Connections per replica.
const POOL_SIZE: usize = 16;

/// How long the service waits for a store call beyond the statement timeout before it gives
/// up on a database that does not answer at all (a hung server enforces no timeout).
pub const ANSWER_MARGIN: Duration = Duration::from_secs(1);

/// A store call's bound while the database is suspected hung (the last call had no answer).
pub const SUSPECT_DEADLINE: Duration = Duration::from_secs(1);

/// Timeouts of the connections to PostgreSQL, so that a hung or unreachable database fails
/// requests with [`StoreError::Unavailable`] (503) within seconds instead of holding them.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PgOptions {
    /// `statement_timeout` of every session (the database cancels a statement that runs
    /// longer); the service also abandons any store call that has no answer after this plus
    /// [`ANSWER_MARGIN`] (a stopped or hung server cancels nothing).
    pub statement_timeout: Duration,
    /// `TCP_USER_TIMEOUT` of every connection (sent data unacknowledged this long closes the
    /// connection), and the keepalive probing that detects a silent peer in about as long.
    pub tcp_user_timeout: Duration,
}

impl Default for PgOptions {
    fn default() -> Self {
        PgOptions {
            statement_timeout: Duration::from_secs(5),
            tcp_user_timeout: Duration::from_secs(10),
        }
    }
}

/// The PostgreSQL engine: a pool of connections to one database. Cheap to clone.
#[derive(Clone)]
pub struct PgStore {
    pool: Pool,
    location: String,
    /// The longest a store call may take (the statement timeout plus [`ANSWER_MARGIN`]).
    deadline: Duration,
    /// Set when a call went unanswered, cleared by the next answer ([`PgStore::bounded`]).
    unanswered: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl PgStore {
    /// Connects to the database at `url` (`postgres://user[:password]@host[:port]/database`),
    /// and brings its schema to the newest version this build knows ([`migrate`]; safe when
    /// several replicas start at once). Fails with [`StoreError::Open`] when the URL is invalid
    /// or the database cannot be reached. Uses the default [`PgOptions`].
    pub async fn connect(url: &str) -> StoreResult<PgStore> {
        PgStore::connect_with(url, &PgOptions::default()).await
    }

    /// [`PgStore::connect`] with these timeouts.
    pub async fn connect_with(url: &str, options: &PgOptions) -> StoreResult<PgStore> {
        let bad_url = |reason: String| StoreError::Open {
            location: "the database URL".into(),
            source: reason.into(),
        };
        let split = tls::split(url).map_err(bad_url)?;
        let connector = tls::client_config(split.mode, split.root_cert.as_deref())
            .map(tokio_postgres_rustls::MakeRustlsConnect::new)
            .map_err(bad_url)?;
        let mut config: tokio_postgres::Config =
            split.url.parse().map_err(|e| StoreError::Open {
                location: "the database URL".into(),
                source: Box::new(e),
            })?;
        config.ssl_mode(tls::driver_mode(split.mode));
        if config.get_connect_timeout().is_none() {
            config.connect_timeout(CONNECT_TIMEOUT);
        }
        if config.get_application_name().is_none() {
            config.application_name("seasonloc");
        }
        config.keepalives(true);
        // Probing starts after a third of the TCP user timeout, three probes over the rest.
        let idle = (options.tcp_user_timeout / 3).max(Duration::from_secs(1));
        config.keepalives_idle(idle);
        config.keepalives_interval((idle / 3).max(Duration::from_secs(1)));
        config.keepalives_retries(3);
        config.tcp_user_timeout(options.tcp_user_timeout);
        // A URL's own `options` keep theirs; ours come after, so they win for this setting.
        let ms = options.statement_timeout.as_millis().max(1);
        let session = match config.get_options() {
            Some(o) if !o.is_empty() => format!("{o} -c statement_timeout={ms}"),
            _ => format!("-c statement_timeout={ms}"),
        };
        config.options(session);
        let location = format!("{} (sslmode={})", describe(&config), split.mode.name());
        let manager = Manager::from_config(
            config,
            connector,
            ManagerConfig {
                recycling_method: RecyclingMethod::Fast,
            },
        );
        let pool = Pool::builder(manager)
            .max_size(POOL_SIZE)
            .runtime(Runtime::Tokio1)
            .wait_timeout(Some(CONNECT_TIMEOUT))
            .create_timeout(Some(CONNECT_TIMEOUT))
            .recycle_timeout(Some(CONNECT_TIMEOUT))
            .build()
            .map_err(|e| StoreError::Open {
                location: location.clone(),
                source: Box::new(e),
            })?;
        let store = PgStore {
            pool,
            location,
            deadline: options.statement_timeout + ANSWER_MARGIN,
            unanswered: Default::default(),
        };
        let mut client = store.client().await.map_err(|e| StoreError::Open {
            location: store.location.clone(),
            source: Box::new(e),
        })?;
        migrate::migrate(&mut client).await?;
        Ok(store)
    }

    /// `call`, abandoned with [`StoreError::Unavailable`] when it has no answer within the
    /// deadline (a hung database). A connection left with a pending statement goes back to
    /// the pool and answers (or is dropped by its TCP timeouts) once the server moves again.
    ///
    /// Once a call has gone unanswered, later calls get only [`SUSPECT_DEADLINE`] until one
    /// is answered: requests queued behind each other (a trip's batches take turns) then fail
    /// one after another within seconds instead of each waiting the full deadline.
    async fn bounded<T>(
        &self,
        call: impl std::future::Future<Output = StoreResult<T>>,
    ) -> StoreResult<T> {
        use std::sync::atomic::Ordering;
        let suspect = self.unanswered.load(Ordering::Relaxed);
        let deadline = if suspect {
            SUSPECT_DEADLINE.min(self.deadline)
        } else {
            self.deadline
        };
        match tokio::time::timeout(deadline, call).await {
            Ok(result) => {
                if suspect {
                    self.unanswered.store(false, Ordering::Relaxed);
                }
                result
            }
            Err(_) => {
                self.unanswered.store(true, Ordering::Relaxed);
                Err(StoreError::Unavailable(format!(
                    "the database did not answer within {} ms",
                    deadline.as_millis()
                )))
            }
        }
    }

    /// A pooled connection.
    async fn client(&self) -> StoreResult<deadpool_postgres::Object> {
        self.pool.get().await.map_err(pool_error)
    }

    /// The schema version of the database.
    pub async fn schema_version(&self) -> StoreResult<u32> {
        let client = self.client().await?;
        migrate::current_version(&client)
            .await?
            .ok_or_else(|| StoreError::Unavailable("the schema is not installed".into()))
    }
}

/// `postgres://user@host:port/database`, without the password.
fn describe(config: &tokio_postgres::Config) -> String {
    use tokio_postgres::config::Host;
    let hosts: Vec<String> = config
        .get_hosts()
        .iter()
        .zip(config.get_ports().iter().chain(std::iter::repeat(&5432)))
        .map(|(h, p)| match h {
            Host::Tcp(name) => format!("{name}:{p}"),
            #[cfg(unix)]
            Host::Unix(path) => format!("{}:{p}", path.display()),
        })
        .collect();
    format!(
        "postgres://{}@{}/{}",
        config.get_user().unwrap_or(""),
        hosts.join(","),
        config.get_dbname().unwrap_or("")
    )
}

/// Whether a database error means "the server cannot be reached or is going away".
fn is_unavailable(e: &tokio_postgres::Error) -> bool {
    if e.is_closed() {
        return true;
    }
    match e.code() {
        Some(code) => {
            code.code().starts_with("08")
                || [
                    SqlState::ADMIN_SHUTDOWN,
                    SqlState::CRASH_SHUTDOWN,
                    SqlState::CANNOT_CONNECT_NOW,
                    SqlState::TOO_MANY_CONNECTIONS,
                    SqlState::T_R_DEADLOCK_DETECTED,
                    SqlState::T_R_SERIALIZATION_FAILURE,
                    // `statement_timeout` ran out: a database too slow to answer now.
                    SqlState::QUERY_CANCELED,
                ]
                .contains(code)
        }
        None => {
            let mut source = std::error::Error::source(e);
            while let Some(s) = source {
                if s.is::<std::io::Error>() {
                    return true;
                }
                source = s.source();
            }
            false
        }
    }
}

/// A database error as a store error (with the server's code and message: `Display` of a
/// server error is only "db error").
pub(crate) fn db_error(e: tokio_postgres::Error) -> StoreError {
    let text = match e.as_db_error() {
        Some(db) => format!("{}: {} ({})", db.severity(), db.message(), db.code().code()),
        None => e.to_string(),
    };
    if is_unavailable(&e) {
        StoreError::Unavailable(format!("the database: {text}"))
    } else {
        StoreError::Backend(text.into())
    }
}

/// A pool error (no connection within the timeouts, or the connection failed) as a store error.
fn pool_error(e: PoolError) -> StoreError {
    match e {
        PoolError::Backend(e) if !is_unavailable(&e) && e.code().is_some() => {
            // The server answered and refused (bad credentials, no such database): still
            // nothing a request can do, and retrying after a fix may succeed.
            // The driver's `Display` says only "db error"; the server's own message names the
            // cause (a password, a database, `pg_hba.conf`, no encryption).
            let why = e
                .as_db_error()
                .map_or_else(|| e.to_string(), |d| d.message().to_string());
            StoreError::Unavailable(format!("the database refused the connection: {why}"))
        }
        other @ (PoolError::Backend(_)
        | PoolError::Timeout(_)
        | PoolError::Closed
        | PoolError::NoRuntimeSpecified
        | PoolError::PostCreateHook(_)) => StoreError::Unavailable(format!(
            "cannot reach the database: {}",
            with_causes(&other)
        )),
    }
}

/// An error's message followed by its causes' (`: `-joined), skipping a cause its parent
/// already ends with: the driver's "error performing TLS handshake" keeps rustls's reason
/// (`invalid peer certificate: UnknownIssuer`) in its source.
fn with_causes(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        let part = c.to_string();
        if !text.ends_with(&part) {
            text.push_str(": ");
            text.push_str(&part);
        }
        cause = c.source();
    }
    text
}

/// An id as stored (`BIGINT`); `None` for ids no sequence value can equal.
fn db_id(id: u64) -> Option<i64> {
    i64::try_from(id).ok()
}

/// A stored non-negative `BIGINT` as `u64`.
fn unsigned(table: &str, id: i64, value: i64) -> StoreResult<u64> {
    u64::try_from(value).map_err(|_| corrupt(table, id, format!("negative value {value}")))
}

/// A stored non-negative `BIGINT` as `u32`.
fn small(table: &str, id: i64, value: i64) -> StoreResult<u32> {
    u32::try_from(value).map_err(|_| corrupt(table, id, format!("value {value} out of range")))
}

/// [`StoreError::Corrupt`] for a row.
fn corrupt(table: &str, id: i64, reason: impl Into<String>) -> StoreError {
    StoreError::corrupt(format!("{table}/{id}").as_bytes(), reason)
}

/// The exclusive upper id bound of a page, as stored.
fn before(page: &PageRequest) -> i64 {
    page.before
        .map_or(i64::MAX, |b| db_id(b).unwrap_or(i64::MAX))
}

/// Rows fetched for a page of `limit`: one more tells whether there is a next page.
fn fetch(page: &PageRequest) -> i64 {
    i64::try_from(page.limit.max(1)).map_or(i64::MAX, |l| l.saturating_add(1))
}

/// Cuts the `limit + 1` rows of a page to a [`Page`].
fn paged<T>(mut items: Vec<T>, limit: usize, id: impl Fn(&T) -> u64) -> Page<T> {
    let limit = limit.max(1);
    let next = if items.len() > limit {
        items.truncate(limit);
        items.last().map(id)
    } else {
        None
    };
    Page { items, next }
}

impl PgStore {
    /// Inserts `record` (with `indices`, for appends) for `map` in `tx`; fails with
    /// [`StoreError::IdempotencyKeyTaken`] when its key is stored already (the transaction is
    /// then rolled back by the caller's `?`).
    async fn claim_key(
        tx: &deadpool_postgres::Transaction<'_>,
        map: i64,
        record: Option<&IdempotencyRecord>,
        indices: Option<Range<u32>>,
    ) -> StoreResult<()> {
        let Some(record) = record else {
            return Ok(());
        };
        let stmt = tx
            .prepare_cached(
                "INSERT INTO idempotency_keys
                     (scope, key, map_id, fingerprint, response, first, count, created_ms)
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8)",
            )
            .await
            .or_store()?;
        let first = indices.as_ref().map(|r| i64::from(r.start));
        let count = indices.as_ref().map(|r| i64::from(r.end - r.start));
        let created = i64::try_from(now_ms()).unwrap_or(i64::MAX);
        match tx
            .execute(
                &stmt,
                &[
                    &record.scope,
                    &record.key,
                    &map,
                    &record.fingerprint,
                    &record.response,
                    &first,
                    &count,
                    &created,
                ],
            )
            .await
        {
            Ok(_) => Ok(()),
            Err(e) if e.code() == Some(&SqlState::UNIQUE_VIOLATION) => {
                Err(StoreError::IdempotencyKeyTaken {
                    scope: record.scope.clone(),
                    key: record.key.clone(),
                })
            }
            Err(e) => Err(db_error(e)),
        }
    }

    async fn idempotency(&self, scope: &str, key: &str) -> StoreResult<Option<IdempotencyRecord>> {
        let client = self.client().await?;
        let stmt = client
            .prepare_cached(
                "SELECT fingerprint, response, first, count FROM idempotency_keys
                 WHERE scope = $1 AND key = $2",
            )
            .await
            .or_store()?;
        let Some(row) = client.query_opt(&stmt, &[&scope, &key]).await.or_store()? else {
            return Ok(None);
        };
        let first: Option<i64> = row.get(2);
        let count: Option<i64> = row.get(3);
        let indices = match (first, count) {
            (Some(f), Some(c)) => {
                let f = small("idempotency_keys", 0, f)?;
                let c = small("idempotency_keys", 0, c)?;
                Some(f..f.saturating_add(c))
            }
            _ => None,
        };
        Ok(Some(IdempotencyRecord {
            scope: scope.to_string(),
            key: key.to_string(),
            fingerprint: row.get(0),
            response: row.get(1),
            indices,
        }))
    }
}

#[async_trait]
impl Store for PgStore {
    fn location(&self) -> String {
        self.location.clone()
    }

    async fn check(&self) -> StoreResult<()> {
        self.bounded(self.schema_version()).await.map(|_| ())
    }

    async fn flush(&self) -> StoreResult<()> {
        // Every commit is durable when it returns.
        Ok(())
    }

    async fn create_map(&self, new: NewMap) -> StoreResult<MapRecord> {
        self.bounded(self.insert_map(new)).await
    }

    async fn get_map(&self, id: u64) -> StoreResult<MapRecord> {
        self.bounded(self.map(id)).await
    }

    async fn list_maps(&self) -> StoreResult<Vec<MapRecord>> {
        self.bounded(self.all_maps()).await
    }

    async fn delete_map(&self, id: u64) -> StoreResult<()> {
        self.bounded(self.remove_map(id)).await
    }

    async fn append_images(&self, batch: ImageBatch) -> StoreResult<Range<u32>> {
        self.bounded(self.append(batch)).await
    }

    async fn descriptors(&self, map: u64, rows: Range<u32>) -> StoreResult<Matrix> {
        self.bounded(self.rows(map, rows)).await
    }

    async fn image_metadata(&self, map: u64, rows: Range<u32>) -> StoreResult<Vec<ImageMeta>> {
        self.bounded(self.metas(map, rows)).await
    }

    async fn thumbnail(&self, map: u64, index: u32) -> StoreResult<Option<Vec<u8>>> {
        self.bounded(self.thumbnail_of(map, index)).await
    }

    async fn cooc_map(&self, map: u64) -> StoreResult<Option<Vec<u8>>> {
        self.bounded(self.cooc(map)).await
    }

    async fn put_cooc_map(&self, write: CoocWrite) -> StoreResult<Range<u32>> {
        self.bounded(self.replace_cooc(write)).await
    }

    async fn create_localization(&self, new: NewLocalization) -> StoreResult<LocalizationRecord> {
        self.bounded(self.insert_localization(new)).await
    }

    async fn get_localization(&self, id: u64) -> StoreResult<LocalizationRecord> {
        self.bounded(self.localization(id)).await
    }

    async fn localization_picture(&self, id: u64) -> StoreResult<Option<Vec<u8>>> {
        self.bounded(self.picture(id)).await
    }

    async fn list_localizations(
        &self,
        map: Option<u64>,
        page: PageRequest,
    ) -> StoreResult<Page<LocalizationRecord>> {
        self.bounded(self.localizations(map, page)).await
    }

    async fn create_trip(&self, new: NewTrip) -> StoreResult<TripRecord> {
        self.bounded(self.insert_trip(new)).await
    }

    async fn get_trip(&self, id: u64) -> StoreResult<TripRecord> {
        self.bounded(self.trip(id)).await
    }

    async fn trip_state(&self, id: u64) -> StoreResult<(TripRecord, TripState)> {
        self.bounded(self.trip_with_state(id)).await
    }

    async fn put_trip_batch(&self, id: u64, batch: TripBatch) -> StoreResult<TripRecord> {
        self.bounded(self.apply_trip_batch(id, batch)).await
    }

    async fn close_trip(&self, id: u64) -> StoreResult<TripRecord> {
        self.bounded(self.close(id)).await
    }

    async fn trip_estimates(&self, id: u64, from: u32) -> StoreResult<Vec<FrameEstimate>> {
        self.bounded(self.estimates(id, from)).await
    }

    async fn list_trips(&self, map: u64, page: PageRequest) -> StoreResult<Page<TripRecord>> {
        self.bounded(self.trips(map, page)).await
    }

    async fn idempotency_record(
        &self,
        scope: &str,
        key: &str,
    ) -> StoreResult<Option<IdempotencyRecord>> {
        self.bounded(self.idempotency(scope, key)).await
    }
}

#[cfg(test)]
mod tests;
