//! Trips: open, extend by a batch, close, read, list by map (newest first, paginated).
//!
//! A trip is its record (`T`), its solver state in parts (opaque bytes owned by `seasonloc_core::trip`:
//! the base `b`, the snapshot `s` and one log row per frame since the snapshot `r`; or, for a
//! trip written by layouts 4-5, one blob `S`) and one estimate per frame (`F`), plus an index
//! entry under its map (`t`); keys in [`super::codec`]. Invariant: the record's `frame_count`,
//! the state and the frames' estimates always describe the same point of the trip — every
//! batch writes its record, state delta (new log rows, sometimes a snapshot and the removal of
//! the log rows before it) and estimates in one atomic `sled::Batch`, flushed before the call
//! returns. Deleting the map deletes its trips (in [`Store::delete_map`](seasonloc_app::store::Store::delete_map)).

use super::{codec, SledStore};
use crate::OrStore;
use seasonloc_app::model::TripRecord;
use seasonloc_app::store::{
    now_ms, IdempotencyRecord, NewTrip, Page, PageRequest, StoreError, StoreResult, TripBatch,
    TripState, TripStateWrite,
};
use seasonloc_core::trip::FrameEstimate;

/// A log row's frame as a key part.
fn log_frame(id: u64, frame: u64) -> StoreResult<u32> {
    u32::try_from(frame).map_err(|_| {
        StoreError::corrupt(&codec::trip_key(id), format!("log frame {frame} over 2^32"))
    })
}

impl SledStore {
    /// Opens a trip on its map with its initial state; fails when the map is gone.
    pub fn create_trip(&self, new: NewTrip) -> StoreResult<TripRecord> {
        let _guard = self.lock();
        self.get_map(new.map_id)?;
        if self
            .db()?
            .contains_key(codec::trip_key(new.id))
            .or_store()?
        {
            return Err(StoreError::IdTaken(new.id));
        }
        let record = TripRecord {
            id: new.id,
            map_id: new.map_id,
            created_ms: now_ms(),
            closed_ms: None,
            frame_count: 0,
            reference_count: new.reference_count,
            status: None,
            params: new.params,
            owner: new.owner,
        };
        let mut batch = sled::Batch::default();
        batch.insert(&codec::trip_key(record.id), codec::encode_trip(&record)?);
        batch.insert(&codec::trip_base_key(record.id), new.base);
        batch.insert(&codec::trip_snapshot_key(record.id), new.snapshot);
        batch.insert(
            &codec::trip_by_map_key(record.map_id, record.id),
            &[] as &[u8],
        );
        self.claim_key(new.idempotency.as_ref(), None, &mut batch)?;
        self.commit(batch)?;
        Ok(record)
    }

    /// One trip's record.
    pub fn get_trip(&self, id: u64) -> StoreResult<TripRecord> {
        let key = codec::trip_key(id);
        match self.db()?.get(key).or_store()? {
            Some(v) => codec::decode_trip(&key, &v),
            None => Err(StoreError::TripNotFound(id)),
        }
    }

    /// A trip's record and solver state, read consistently (under the write lock).
    pub fn trip_state(&self, id: u64) -> StoreResult<(TripRecord, TripState)> {
        let _guard = self.lock();
        let record = self.get_trip(id)?;
        let Some(base) = self.db()?.get(codec::trip_base_key(id)).or_store()? else {
            let key = codec::trip_state_key(id);
            let state = self
                .db()?
                .get(key)
                .or_store()?
                .ok_or_else(|| StoreError::corrupt(&key, "the trip has no state"))?;
            return Ok((record, TripState::Legacy(state.to_vec())));
        };
        let key = codec::trip_snapshot_key(id);
        let snapshot = self
            .db()?
            .get(key)
            .or_store()?
            .ok_or_else(|| StoreError::corrupt(&key, "the trip has a base but no snapshot"))?;
        let log = self
            .db()?
            .scan_prefix(codec::trip_log_prefix(id))
            .map(|kv| {
                let (k, v) = kv.or_store()?;
                Ok((u64::from(codec::log_frame_at(&k)?), v.to_vec()))
            })
            .collect::<StoreResult<Vec<_>>>()?;
        Ok((
            record,
            TripState::Parts {
                base: base.to_vec(),
                snapshot: snapshot.to_vec(),
                log,
            },
        ))
    }

    /// Adds a batch's state delta to `batch`.
    fn write_state(
        &self,
        id: u64,
        write: TripStateWrite,
        batch: &mut sled::Batch,
    ) -> StoreResult<()> {
        if let Some(base) = write.base {
            batch.insert(&codec::trip_base_key(id), base);
            batch.remove(&codec::trip_state_key(id));
        }
        if let Some(snapshot) = write.snapshot {
            batch.insert(&codec::trip_snapshot_key(id), snapshot);
        }
        if let Some(before) = write.drop_log_before {
            let end = codec::trip_log_key(id, log_frame(id, before)?);
            for kv in self.db()?.range(codec::trip_log_key(id, 0)..end) {
                batch.remove(kv.or_store()?.0);
            }
        }
        for (frame, row) in write.log {
            batch.insert(&codec::trip_log_key(id, log_frame(id, frame)?), row);
        }
        Ok(())
    }

    /// Stores one batch's result: record, state and estimates in one atomic, flushed write.
    /// Fails without writing when the trip is gone, closed, or has moved on since
    /// `expected_frames`.
    pub fn put_trip_batch(&self, id: u64, write: TripBatch) -> StoreResult<TripRecord> {
        let _guard = self.lock();
        let mut record = self.get_trip(id)?;
        if record.closed_ms.is_some() {
            return Err(StoreError::TripClosed(id));
        }
        if record.frame_count != write.expected_frames {
            return Err(StoreError::TripConflict {
                id,
                stored: record.frame_count,
                expected: write.expected_frames,
            });
        }
        record.frame_count = write.frame_count;
        record.status = Some(write.status);
        let mut batch = sled::Batch::default();
        batch.insert(&codec::trip_key(id), codec::encode_trip(&record)?);
        self.write_state(id, write.state, &mut batch)?;
        for e in &write.estimates {
            batch.insert(
                &codec::trip_frame_key(id, codec::small_index(e.frame)?),
                codec::encode_frame(e)?,
            );
        }
        self.claim_key(write.idempotency.as_ref(), None, &mut batch)?;
        self.commit(batch)?;
        Ok(record)
    }

    /// Closes a trip (idempotent: closing twice keeps the first time).
    pub fn close_trip(&self, id: u64) -> StoreResult<TripRecord> {
        let _guard = self.lock();
        let mut record = self.get_trip(id)?;
        if record.closed_ms.is_none() {
            record.closed_ms = Some(now_ms());
            let mut batch = sled::Batch::default();
            batch.insert(&codec::trip_key(id), codec::encode_trip(&record)?);
            self.commit(batch)?;
        }
        Ok(record)
    }

    /// Every frame's latest estimate, in frame order.
    pub fn trip_estimates(&self, id: u64, from: u32) -> StoreResult<Vec<FrameEstimate>> {
        self.get_trip(id)?;
        self.db()?
            .range(codec::trip_frame_key(id, from)..=codec::trip_frame_key(id, u32::MAX))
            .map(|kv| {
                let (k, v) = kv.or_store()?;
                codec::decode_frame(&k, &v)
            })
            .collect()
    }

    /// A page of `map`'s trips, newest first (the map must exist).
    pub fn list_trips(&self, map: u64, page: PageRequest) -> StoreResult<Page<TripRecord>> {
        self.get_map(map)?;
        let lo = codec::trip_by_map_key(map, 0);
        let hi = codec::trip_by_map_key(map, page.before.unwrap_or(u64::MAX));
        self.page(&lo, &hi, 9, page.limit, |id| self.get_trip(id))
    }

    /// Adds the removal of every trip of `map` (records, states, frames, index) to `batch`.
    pub(super) fn remove_trips(&self, map: u64, batch: &mut sled::Batch) -> StoreResult<()> {
        for kv in self.db()?.scan_prefix(codec::trips_by_map_prefix(map)) {
            let (k, _) = kv.or_store()?;
            let trip = codec::id_at(&k, 9)?;
            batch.remove(&codec::trip_key(trip));
            batch.remove(&codec::trip_state_key(trip));
            batch.remove(&codec::trip_base_key(trip));
            batch.remove(&codec::trip_snapshot_key(trip));
            for kv in self.db()?.scan_prefix(codec::trip_log_prefix(trip)) {
                batch.remove(kv.or_store()?.0);
            }
            for kv in self.db()?.scan_prefix(codec::trip_frames_prefix(trip)) {
                batch.remove(kv.or_store()?.0);
            }
            self.remove_keys(&IdempotencyRecord::trip_scope(trip), batch)?;
            batch.remove(k);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sled::test_map as map;
    use seasonloc_core::calibration::FrameStatus;
    use seasonloc_core::trip::{TripParams, TripStatus};

    fn new_trip(map_id: u64, reference_count: u32, state: u8) -> NewTrip {
        NewTrip {
            id: crate::test_id(),
            map_id,
            reference_count,
            params: TripParams::default(),
            owner: None,
            base: vec![b'B', state],
            snapshot: vec![b'S', state],
            idempotency: None,
        }
    }

    fn page(before: Option<u64>, limit: usize) -> PageRequest {
        PageRequest { before, limit }
    }

    /// A batch of `n` frames after `expected`: one log row per frame, a snapshot at
    /// `expected` (dropping the rows before it) when `snapshot` is set.
    fn write(expected: u64, n: u64, snapshot: Option<u8>) -> TripBatch {
        TripBatch {
            expected_frames: expected,
            frame_count: expected + n,
            status: TripStatus::Localized,
            state: TripStateWrite {
                base: None,
                snapshot: snapshot.map(|s| vec![b'S', s]),
                log: (expected..expected + n)
                    .map(|f| (f, vec![f as u8; 3]))
                    .collect(),
                drop_log_before: snapshot.map(|_| expected),
            },
            estimates: (expected..expected + n)
                .map(|f| FrameEstimate {
                    frame: f as usize,
                    reference: (f % 2 == 0).then_some(f as usize * 2),
                    confidence: f as f64 / 10.0,
                    p_correct: f as f64 / 100.0,
                    status: FrameStatus::ALL[f as usize % 4],
                })
                .collect(),
            idempotency: None,
        }
    }

    fn parts(store: &SledStore, id: u64) -> (Vec<u8>, Vec<u8>, Vec<u64>) {
        match store.trip_state(id).unwrap().1 {
            TripState::Parts {
                base,
                snapshot,
                log,
            } => (base, snapshot, log.into_iter().map(|(f, _)| f).collect()),
            TripState::Legacy(_) => panic!("legacy state"),
        }
    }

    #[test]
    fn batches_update_record_state_and_estimates_together() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let m = map(&store);
        let t = store.create_trip(new_trip(m, 7, 0)).unwrap();
        assert_eq!(parts(&store, t.id), (vec![b'B', 0], vec![b'S', 0], vec![]));
        store.put_trip_batch(t.id, write(0, 3, None)).unwrap();
        let r = store.put_trip_batch(t.id, write(3, 2, None)).unwrap();
        assert_eq!(r.frame_count, 5);
        assert_eq!(parts(&store, t.id).2, vec![0, 1, 2, 3, 4]);
        // A stale batch (computed after 3 frames) is refused and changes nothing.
        assert!(matches!(
            store.put_trip_batch(t.id, write(3, 2, Some(9))),
            Err(StoreError::TripConflict { stored: 5, .. })
        ));
        assert_eq!(parts(&store, t.id).1, vec![b'S', 0]);
        // A snapshot replaces the stored one and drops the log rows before it.
        store.put_trip_batch(t.id, write(5, 2, Some(2))).unwrap();
        let (rec, state) = store.trip_state(t.id).unwrap();
        assert_eq!(rec.frame_count, 7);
        assert_eq!(
            state,
            TripState::Parts {
                base: vec![b'B', 0],
                snapshot: vec![b'S', 2],
                log: vec![(5, vec![5; 3]), (6, vec![6; 3])],
            }
        );
        let est = store.trip_estimates(t.id, 0).unwrap();
        assert_eq!(est.len(), 7);
        assert_eq!(est[4].reference, Some(8));
        assert_eq!(est[3].reference, None);
        store.close_trip(t.id).unwrap();
        assert!(matches!(
            store.put_trip_batch(t.id, write(7, 1, None)),
            Err(StoreError::TripClosed(_))
        ));
        // Reopening the store keeps everything.
        drop(store);
        let store = SledStore::open(dir.path()).unwrap();
        assert_eq!(store.trip_estimates(t.id, 0).unwrap(), est);
        assert_eq!(store.trip_state(t.id).unwrap().1, state);
        assert!(store.get_trip(t.id).unwrap().closed_ms.is_some());
    }

    #[test]
    fn a_one_blob_state_is_read_as_legacy_and_replaced_by_a_base() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let m = map(&store);
        let t = store.create_trip(new_trip(m, 7, 0)).unwrap();
        // What layouts 4-5 stored: the blob under `S`, no parts.
        store
            .db()
            .unwrap()
            .remove(codec::trip_base_key(t.id))
            .unwrap();
        store
            .db()
            .unwrap()
            .remove(codec::trip_snapshot_key(t.id))
            .unwrap();
        store
            .db()
            .unwrap()
            .insert(codec::trip_state_key(t.id), vec![7u8; 5])
            .unwrap();
        assert_eq!(
            store.trip_state(t.id).unwrap().1,
            TripState::Legacy(vec![7; 5])
        );
        let mut first = write(0, 2, Some(1));
        first.state.base = Some(vec![b'B', 1]);
        store.put_trip_batch(t.id, first).unwrap();
        assert_eq!(
            parts(&store, t.id),
            (vec![b'B', 1], vec![b'S', 1], vec![0, 1])
        );
        assert!(store
            .db()
            .unwrap()
            .get(codec::trip_state_key(t.id))
            .unwrap()
            .is_none());
    }

    #[test]
    fn lists_newest_first_and_map_deletion_removes_trips() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let (a, b) = (map(&store), map(&store));
        let mut mine = Vec::new();
        for _ in 0..5 {
            mine.push(store.create_trip(new_trip(a, 1, 1)).unwrap().id);
            store.create_trip(new_trip(b, 1, 1)).unwrap();
        }
        let p1 = store.list_trips(a, page(None, 2)).unwrap();
        assert_eq!(
            p1.items.iter().map(|t| t.id).collect::<Vec<_>>(),
            vec![mine[4], mine[3]]
        );
        let p2 = store.list_trips(a, page(p1.next, 2)).unwrap();
        let p3 = store.list_trips(a, page(p2.next, 2)).unwrap();
        assert_eq!(p3.items.len(), 1);
        assert_eq!(p3.next, None);
        store.put_trip_batch(mine[0], write(0, 4, None)).unwrap();
        store.delete_map(a).unwrap();
        assert!(matches!(
            store.get_trip(mine[0]),
            Err(StoreError::TripNotFound(_))
        ));
        for prefix in [
            codec::trip_frames_prefix(mine[0]),
            codec::trip_log_prefix(mine[0]),
            codec::trip_base_key(mine[0]),
            codec::trip_snapshot_key(mine[0]),
        ] {
            assert!(store.db().unwrap().scan_prefix(prefix).next().is_none());
        }
        assert_eq!(store.list_trips(b, page(None, 10)).unwrap().items.len(), 5);
        assert!(matches!(
            store.list_trips(a, page(None, 10)),
            Err(StoreError::MapNotFound(_))
        ));
        assert!(matches!(
            store.create_trip(new_trip(a, 1, 2)),
            Err(StoreError::MapNotFound(_))
        ));
    }
}
