//! Trips: open, extend by a batch, close, read, list by map (newest first, paginated).
//!
//! A trip is three kinds of keys (see [`super::codec`]): its record (`T`), its solver state
//! (`S`, opaque bytes owned by `crate::trip`) and one estimate per frame (`F`), plus an index
//! entry under its map (`t`). Invariant: the record's `frame_count`, the state and the frames'
//! estimates always describe the same point of the trip — every batch writes all three in
//! one atomic `sled::Batch`, flushed before the call returns. Deleting the map deletes its
//! trips (in [`Store::delete_map`]).

use super::{codec, SledStore};
use crate::store::{
    now_ms, FrameRecord, IdempotencyRecord, NewTrip, Page, PageRequest, StoreError, StoreResult,
    TripBatch, TripRecord,
};

impl SledStore {
    /// Opens a trip on its map with its initial state; fails when the map is gone.
    pub fn create_trip(&self, new: NewTrip) -> StoreResult<TripRecord> {
        let _guard = self.lock();
        self.get_map(new.map_id)?;
        if self.db.contains_key(codec::trip_key(new.id))? {
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
        };
        let mut batch = sled::Batch::default();
        batch.insert(&codec::trip_key(record.id), codec::encode_trip(&record)?);
        batch.insert(&codec::trip_state_key(record.id), new.state);
        batch.insert(
            &codec::trip_by_map_key(record.map_id, record.id),
            &[] as &[u8],
        );
        self.db.apply_batch(batch)?;
        self.db.flush()?;
        Ok(record)
    }

    /// One trip's record.
    pub fn get_trip(&self, id: u64) -> StoreResult<TripRecord> {
        let key = codec::trip_key(id);
        match self.db.get(key)? {
            Some(v) => codec::decode_trip(&key, &v),
            None => Err(StoreError::TripNotFound(id)),
        }
    }

    /// A trip's record and solver state, read consistently (under the write lock).
    pub fn trip_state(&self, id: u64) -> StoreResult<(TripRecord, Vec<u8>)> {
        let _guard = self.lock();
        let record = self.get_trip(id)?;
        let key = codec::trip_state_key(id);
        let state = self
            .db
            .get(key)?
            .ok_or_else(|| StoreError::corrupt(&key, "the trip has no state"))?;
        Ok((record, state.to_vec()))
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
        batch.insert(&codec::trip_state_key(id), write.state);
        for e in &write.estimates {
            batch.insert(&codec::trip_frame_key(id, e.frame), codec::encode_frame(e));
        }
        self.claim_key(write.idempotency.as_ref(), None, &mut batch)?;
        self.db.apply_batch(batch)?;
        self.db.flush()?;
        Ok(record)
    }

    /// Closes a trip (idempotent: closing twice keeps the first time).
    pub fn close_trip(&self, id: u64) -> StoreResult<TripRecord> {
        let _guard = self.lock();
        let mut record = self.get_trip(id)?;
        if record.closed_ms.is_none() {
            record.closed_ms = Some(now_ms());
            self.db
                .insert(codec::trip_key(id), codec::encode_trip(&record)?)?;
            self.db.flush()?;
        }
        Ok(record)
    }

    /// Every frame's latest estimate, in frame order.
    pub fn trip_estimates(&self, id: u64, from: u32) -> StoreResult<Vec<FrameRecord>> {
        self.get_trip(id)?;
        self.db
            .range(codec::trip_frame_key(id, from)..=codec::trip_frame_key(id, u32::MAX))
            .map(|kv| {
                let (k, v) = kv?;
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
        for kv in self.db.scan_prefix(codec::trips_by_map_prefix(map)) {
            let (k, _) = kv?;
            let trip = codec::id_at(&k, 9)?;
            batch.remove(&codec::trip_key(trip));
            batch.remove(&codec::trip_state_key(trip));
            for kv in self.db.scan_prefix(codec::trip_frames_prefix(trip)) {
                batch.remove(kv?.0);
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
    use crate::store::sled::test_map as map;
    use crate::store::TripParamsDocument;
    use crate::trip::{TripParams, TripStatus};

    fn new_trip(map_id: u64, reference_count: u32, state: Vec<u8>) -> NewTrip {
        NewTrip {
            id: crate::store::test_id(),
            map_id,
            reference_count,
            params: TripParamsDocument::from(&TripParams::default()),
            state,
        }
    }

    fn page(before: Option<u64>, limit: usize) -> PageRequest {
        PageRequest { before, limit }
    }

    fn write(expected: u64, n: u64, state: u8) -> TripBatch {
        TripBatch {
            expected_frames: expected,
            frame_count: expected + n,
            status: TripStatus::Localized,
            state: vec![state; 3],
            estimates: (expected..expected + n)
                .map(|f| FrameRecord {
                    frame: f as u32,
                    reference: (f % 2 == 0).then_some(f as u32 * 2),
                    confidence: f as f64 / 10.0,
                })
                .collect(),
            idempotency: None,
        }
    }

    #[test]
    fn batches_update_record_state_and_estimates_together() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let m = map(&store);
        let t = store.create_trip(new_trip(m, 7, vec![0])).unwrap();
        assert_eq!(store.trip_state(t.id).unwrap().1, vec![0]);
        store.put_trip_batch(t.id, write(0, 3, 1)).unwrap();
        let r = store.put_trip_batch(t.id, write(3, 2, 2)).unwrap();
        assert_eq!(r.frame_count, 5);
        // A stale batch (computed after 3 frames) is refused and changes nothing.
        assert!(matches!(
            store.put_trip_batch(t.id, write(3, 2, 9)),
            Err(StoreError::TripConflict { stored: 5, .. })
        ));
        let (rec, state) = store.trip_state(t.id).unwrap();
        assert_eq!((rec.frame_count, state), (5, vec![2; 3]));
        let est = store.trip_estimates(t.id, 0).unwrap();
        assert_eq!(est.len(), 5);
        assert_eq!(est[4].reference, Some(8));
        assert_eq!(est[3].reference, None);
        store.close_trip(t.id).unwrap();
        assert!(matches!(
            store.put_trip_batch(t.id, write(5, 1, 3)),
            Err(StoreError::TripClosed(_))
        ));
        // Reopening the store keeps everything.
        drop(store);
        let store = SledStore::open(dir.path()).unwrap();
        assert_eq!(store.trip_estimates(t.id, 0).unwrap(), est);
        assert!(store.get_trip(t.id).unwrap().closed_ms.is_some());
    }

    #[test]
    fn lists_newest_first_and_map_deletion_removes_trips() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let (a, b) = (map(&store), map(&store));
        let mut mine = Vec::new();
        for _ in 0..5 {
            mine.push(store.create_trip(new_trip(a, 1, vec![1])).unwrap().id);
            store.create_trip(new_trip(b, 1, vec![1])).unwrap();
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
        store.put_trip_batch(mine[0], write(0, 4, 1)).unwrap();
        store.delete_map(a).unwrap();
        assert!(matches!(
            store.get_trip(mine[0]),
            Err(StoreError::TripNotFound(_))
        ));
        assert!(store
            .db
            .scan_prefix(codec::trip_frames_prefix(mine[0]))
            .next()
            .is_none());
        assert_eq!(store.list_trips(b, page(None, 10)).unwrap().items.len(), 5);
        assert!(matches!(
            store.list_trips(a, page(None, 10)),
            Err(StoreError::MapNotFound(_))
        ));
        assert!(matches!(
            store.create_trip(new_trip(a, 1, vec![])),
            Err(StoreError::MapNotFound(_))
        ));
    }
}
