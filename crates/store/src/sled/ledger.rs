//! The ledger: a tiny file beside sled's own (`seasonloc.ledger` in the data folder) that
//! records the generation of the newest acknowledged write, so a store file that was
//! truncated or rolled back to an older, self-consistent state is recognised at start
//! instead of served with data silently missing.
//!
//! Why a separate file: sled recovers a damaged log by cutting it at the first bad message,
//! which leaves a consistent store of an *older* time; nothing inside that file can say that
//! newer writes were ever acknowledged. Every write batch of the engine also stores its
//! generation (`meta/generation`, one more key in the same atomic batch); after sled's flush
//! the ledger is overwritten in place with that generation and synced, then the write is
//! acknowledged. At start the store's generation must be at least the ledger's (it is one
//! higher after a crash between sled's flush and the ledger's sync, never lower unless
//! acknowledged writes are gone).
//!
//! The file is 64 bytes: two 32-byte slots, each `SLLEDGR1` + the generation (`u64` LE) + an
//! FNV-1a 64 checksum of the first 16 bytes + 8 zero bytes. Generation `g` goes to slot
//! `g % 2`, so a torn write can only damage the slot being written and the other still holds
//! the previous generation. The cost on the write path is one 32-byte in-place write and one
//! `fdatasync` of a file whose blocks are already allocated (so it needs no free space).

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use seasonloc_app::store::{StoreError, StoreResult};

/// The ledger's file name in the data folder.
pub const FILE_NAME: &str = "seasonloc.ledger";

const MAGIC: &[u8; 8] = b"SLLEDGR1";
const SLOT: usize = 32;

/// What the ledger file holds when the store opens.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Found {
    /// No ledger file (a new store, or one written before the ledger existed, or an operator
    /// who removed it to accept the store as it is).
    Missing,
    /// The newest generation recorded.
    Generation(u64),
    /// A file without any valid slot.
    Unreadable(String),
}

/// An open ledger file.
#[derive(Debug)]
pub struct Ledger {
    file: File,
    path: PathBuf,
}

fn checksum(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325_u64, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x0100_0000_01b3)
    })
}

fn slot(generation: u64) -> [u8; SLOT] {
    let mut s = [0u8; SLOT];
    s[..8].copy_from_slice(MAGIC);
    s[8..16].copy_from_slice(&generation.to_le_bytes());
    let sum = checksum(&s[..16]);
    s[16..24].copy_from_slice(&sum.to_le_bytes());
    s
}

fn decode(s: &[u8]) -> Option<u64> {
    if s.len() != SLOT || &s[..8] != MAGIC {
        return None;
    }
    let sum = u64::from_le_bytes(s[16..24].try_into().ok()?);
    let generation = u64::from_le_bytes(s[8..16].try_into().ok()?);
    (sum == checksum(&s[..16])).then_some(generation)
}

fn io_error(path: &Path, what: &str, e: std::io::Error) -> StoreError {
    if crate::sled::is_storage_full(&e) {
        StoreError::StorageFull(format!("{what} {}: {e}", path.display()))
    } else {
        StoreError::Backend(format!("{what} {}: {e}", path.display()).into())
    }
}

/// Reads the ledger of the data folder `dir`.
pub fn read(dir: &Path) -> StoreResult<Found> {
    let path = dir.join(FILE_NAME);
    let mut bytes = Vec::new();
    match File::open(&path) {
        Ok(mut f) => f
            .read_to_end(&mut bytes)
            .map_err(|e| io_error(&path, "cannot read the ledger", e))?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Found::Missing),
        Err(e) => return Err(io_error(&path, "cannot open the ledger", e)),
    };
    let best = bytes.chunks(SLOT).filter_map(decode).max();
    Ok(match best {
        Some(g) => Found::Generation(g),
        None => Found::Unreadable(format!(
            "the ledger {} ({} bytes) holds no valid record",
            path.display(),
            bytes.len()
        )),
    })
}

impl Ledger {
    /// Opens the ledger of `dir` and sets it to `generation` (creating the file, and syncing
    /// the folder so the new name is durable, when it is missing).
    pub fn create_or_set(dir: &Path, generation: u64) -> StoreResult<Ledger> {
        let path = dir.join(FILE_NAME);
        let existed = path.exists();
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| io_error(&path, "cannot open the ledger", e))?;
        let mut ledger = Ledger { file, path };
        // Both slots, so the file has its full size and a later write needs no new block.
        let mut both = [0u8; 2 * SLOT];
        both[..SLOT].copy_from_slice(&slot(generation));
        both[SLOT..].copy_from_slice(&slot(generation));
        ledger.write_at(0, &both)?;
        if !existed {
            if let Ok(d) = File::open(dir) {
                // Best effort: some file systems cannot sync a folder.
                let _ = d.sync_all();
            }
        }
        Ok(ledger)
    }

    fn write_at(&mut self, offset: u64, bytes: &[u8]) -> StoreResult<()> {
        let path = self.path.clone();
        let err = |e| io_error(&path, "cannot write the ledger", e);
        self.file.seek(SeekFrom::Start(offset)).map_err(err)?;
        self.file.write_all(bytes).map_err(err)?;
        self.file.sync_data().map_err(err)
    }

    /// Records that writes up to `generation` are durable in the store (before they are
    /// acknowledged).
    pub fn record(&mut self, generation: u64) -> StoreResult<()> {
        self.write_at((generation % 2) * SLOT as u64, &slot(generation))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_newest_valid_slot_wins_and_a_torn_slot_falls_back() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(read(dir.path()).unwrap(), Found::Missing);
        let mut l = Ledger::create_or_set(dir.path(), 7).unwrap();
        assert_eq!(read(dir.path()).unwrap(), Found::Generation(7));
        l.record(8).unwrap();
        assert_eq!(read(dir.path()).unwrap(), Found::Generation(8));
        // Tear the slot of generation 8: the ledger falls back to 7.
        let path = dir.path().join(FILE_NAME);
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[9] ^= 0xff;
        std::fs::write(&path, &bytes).unwrap();
        assert_eq!(read(dir.path()).unwrap(), Found::Generation(7));
        std::fs::write(&path, [0u8; 64]).unwrap();
        assert!(matches!(read(dir.path()).unwrap(), Found::Unreadable(_)));
    }
}
