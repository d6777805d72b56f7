//! Schema migrations of the PostgreSQL engine: the SQL files of `migrations/postgres/`,
//! compiled into the binary and applied in order at start-up.
//!
//! Several replicas may start at once against one database, so the whole check-and-apply runs
//! under a session-level advisory lock ([`LOCK_KEY`]): the first replica applies what is
//! missing, the others wait, then find nothing to do. Each file runs in its own transaction
//! together with its row in `seasonloc_schema`, so a crash mid-migration leaves the previous
//! version intact. A database whose version is newer than this build knows is refused
//! ([`StoreError::UnsupportedSchema`]): an old replica must not write a newer schema.

use crate::OrStore;
use tokio_postgres::Client;

use seasonloc_app::store::{now_ms, StoreError, StoreResult};

/// The advisory lock held while migrating (an arbitrary constant: "seasonlc" in ASCII).
pub const LOCK_KEY: i64 = 0x7365_6173_6f6e_6c63;

/// The migrations, oldest first: version, name, SQL.
pub const MIGRATIONS: &[(u32, &str, &str)] = &[
    (
        1,
        "0001_initial",
        include_str!("../../../../migrations/postgres/0001_initial.sql"),
    ),
    (
        2,
        "0002_idempotency",
        include_str!("../../../../migrations/postgres/0002_idempotency.sql"),
    ),
    (
        3,
        "0003_thumbnails_and_pictures",
        include_str!("../../../../migrations/postgres/0003_thumbnails_and_pictures.sql"),
    ),
    (
        4,
        "0004_trip_state_parts",
        include_str!("../../../../migrations/postgres/0004_trip_state_parts.sql"),
    ),
    (
        5,
        "0005_frame_trust",
        include_str!("../../../../migrations/postgres/0005_frame_trust.sql"),
    ),
    (
        6,
        "0006_trip_owner",
        include_str!("../../../../migrations/postgres/0006_trip_owner.sql"),
    ),
];

/// The newest schema version this build knows.
pub fn newest_version() -> u32 {
    MIGRATIONS.last().map_or(0, |m| m.0)
}

/// The applied schema version, `None` on a database seasonloc has never used.
pub async fn current_version(client: &Client) -> StoreResult<Option<u32>> {
    let exists: bool = client
        .query_one("SELECT to_regclass('seasonloc_schema') IS NOT NULL", &[])
        .await
        .or_store()?
        .get(0);
    if !exists {
        return Ok(None);
    }
    let v: Option<i32> = client
        .query_one("SELECT max(version) FROM seasonloc_schema", &[])
        .await
        .or_store()?
        .get(0);
    Ok(v.map(|v| u32::try_from(v).unwrap_or(0)))
}

/// Brings the schema to [`newest_version`], holding [`LOCK_KEY`] meanwhile. The session's
/// `statement_timeout` (a request's bound) is lifted meanwhile: waiting for another replica's
/// migration, or a long step, is not a hung database.
pub async fn migrate(client: &mut Client) -> StoreResult<()> {
    client
        .batch_execute("SET statement_timeout = 0")
        .await
        .or_store()?;
    client
        .execute("SELECT pg_advisory_lock($1)", &[&LOCK_KEY])
        .await
        .or_store()?;
    let result = apply_missing(client).await;
    let unlocked = client
        .execute("SELECT pg_advisory_unlock($1)", &[&LOCK_KEY])
        .await;
    let reset = client.batch_execute("RESET statement_timeout").await;
    result?;
    unlocked.or_store()?;
    reset.or_store()?;
    Ok(())
}

async fn apply_missing(client: &mut Client) -> StoreResult<()> {
    client
        .batch_execute(
            "CREATE TABLE IF NOT EXISTS seasonloc_schema (
                 version    INTEGER PRIMARY KEY,
                 name       TEXT    NOT NULL,
                 applied_ms BIGINT  NOT NULL
             )",
        )
        .await
        .or_store()?;
    let current = current_version(client).await?.unwrap_or(0);
    if current > newest_version() {
        return Err(StoreError::UnsupportedSchema {
            found: current,
            supported: newest_version(),
        });
    }
    for &(version, name, sql) in MIGRATIONS.iter().filter(|m| m.0 > current) {
        let tx = client.transaction().await.or_store()?;
        tx.batch_execute(sql).await.or_store()?;
        let applied = i64::try_from(now_ms()).unwrap_or(i64::MAX);
        tx.execute(
            "INSERT INTO seasonloc_schema (version, name, applied_ms) VALUES ($1, $2, $3)",
            &[&i32::try_from(version).unwrap_or(i32::MAX), &name, &applied],
        )
        .await
        .or_store()?;
        tx.commit().await.or_store()?;
        tracing::info!(version, name, "database schema migrated");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn versions_increase_from_one() {
        for (k, m) in MIGRATIONS.iter().enumerate() {
            assert_eq!(m.0 as usize, k + 1, "{}", m.1);
            assert!(m.1.starts_with(&format!("{:04}_", m.0)), "{}", m.1);
        }
    }
}
