//! The start-up consistency check of the embedded store: a damaged store is refused with
//! [`StoreError::Damaged`] (a clear message, a non-zero exit of `serve`) instead of being served
//! with data silently missing, or failing request by request.
//!
//! Two checks, both before the store takes a request:
//!
//! * **every record is read once** (every key and value of every tree): sled checks each
//!   message it loads from disk against its CRC, so flipped bytes or zeroed pages in live data
//!   fail here rather than as a 500 (or a panic) on the request that first reads them. The cost
//!   is one sequential read of the store at start, nothing on the write path;
//! * **the generation**: the store's `meta/generation` (stored in every write batch) must be
//!   at least the [`ledger`]'s, else acknowledged writes are missing (a
//!   truncated or rolled-back file that sled recovered to an older, consistent state).
//!
//! A panic inside sled while it opens or reads a damaged file is caught
//! ([`catch`]) and reported as damage too.

use std::path::Path;

use seasonloc_app::store::{StoreError, StoreResult};

use super::{codec, ledger};

/// What the check read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Checked {
    /// The store's generation (0 for a store that never took a write with a generation).
    pub generation: u64,
    /// Records read.
    pub records: u64,
    /// Bytes of keys and values read.
    pub bytes: u64,
}

/// [`StoreError::Damaged`] for the store in `dir`.
pub fn damaged(dir: &Path, reason: impl Into<String>) -> StoreError {
    StoreError::Damaged {
        location: dir.display().to_string(),
        reason: reason.into(),
    }
}

/// Runs `f`, turning a panic (sled asserting on bytes it cannot parse) into
/// [`StoreError::Damaged`].
pub fn catch<T>(dir: &Path, what: &str, f: impl FnOnce() -> StoreResult<T>) -> StoreResult<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(payload) => {
            let msg = payload
                .downcast_ref::<&str>()
                .map(|s| (*s).to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "no message".into());
            Err(damaged(
                dir,
                format!("the storage engine failed an internal check while {what}: {msg}"),
            ))
        }
    }
}

/// The generation stored in `db`.
pub fn generation(db: &sled::Db) -> StoreResult<u64> {
    match db
        .get(codec::GENERATION_KEY)
        .map_err(|e| StoreError::Backend(Box::new(e)))?
    {
        None => Ok(0),
        Some(v) => {
            let b: [u8; 8] = v
                .as_ref()
                .try_into()
                .map_err(|_| StoreError::corrupt(codec::GENERATION_KEY, "expected 8 bytes"))?;
            Ok(u64::from_be_bytes(b))
        }
    }
}

/// Checks the generation of `db` against the ledger in `dir`.
pub fn against_ledger(db: &sled::Db, dir: &Path) -> StoreResult<u64> {
    let stored = generation(db).map_err(|e| damaged(dir, format!("{e}")))?;
    match ledger::read(dir)? {
        ledger::Found::Missing => {
            tracing::info!(
                generation = stored,
                "no ledger in the data folder: starting one at the store's generation"
            );
            Ok(stored)
        }
        ledger::Found::Unreadable(why) => Err(damaged(
            dir,
            format!(
                "{why}; if the store itself is intact, remove {} to accept it as it is",
                ledger::FILE_NAME
            ),
        )),
        ledger::Found::Generation(acked) if stored < acked => Err(damaged(
            dir,
            format!(
                "it holds writes up to generation {stored}, but writes up to {acked} were \
                 acknowledged ({} missing: the store file was truncated, rolled back or damaged \
                 in places)",
                acked - stored
            ),
        )),
        ledger::Found::Generation(_) => Ok(stored),
    }
}

/// Reads every record of every tree of `db`, then checks the generation.
pub fn full(db: &sled::Db, dir: &Path) -> StoreResult<Checked> {
    let mut records = 0u64;
    let mut bytes = 0u64;
    for name in db.tree_names() {
        let tree = db.open_tree(&name).map_err(|e| {
            damaged(
                dir,
                format!("cannot open tree {}: {e}", String::from_utf8_lossy(&name)),
            )
        })?;
        for kv in tree.iter() {
            let (k, v) = kv
                .map_err(|e| damaged(dir, format!("reading record {} failed: {e}", records + 1)))?;
            records += 1;
            bytes += (k.len() + v.len()) as u64;
        }
    }
    let generation = against_ledger(db, dir)?;
    Ok(Checked {
        generation,
        records,
        bytes,
    })
}
