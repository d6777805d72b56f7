//! Stored localization results: put, get, and list (all or by map, newest first, paginated by
//! an exclusive `before` id).

use super::{codec, now_ms, LocalizationRecord, Store, StoreError, StoreResult};

/// One page of a localization listing.
pub type Page = super::Page<LocalizationRecord>;

impl Store {
    /// A fresh localization id, larger than every earlier one.
    pub fn new_localization_id(&self) -> StoreResult<u64> {
        self.next_id()
    }

    /// Stores a result (document chosen by the caller) for `map_id`, atomically with its index
    /// entry, flushed. Fails with [`StoreError::MapNotFound`] when the map is gone.
    pub fn put_localization(&self, id: u64, map_id: u64, document: Vec<u8>) -> StoreResult<u64> {
        let _guard = self.lock();
        self.get_map(map_id)?;
        let created_ms = now_ms();
        let record = LocalizationRecord {
            id,
            map_id,
            created_ms,
            document,
        };
        let mut batch = sled::Batch::default();
        batch.insert(
            &codec::localization_key(id),
            codec::encode_localization(&record),
        );
        batch.insert(&codec::by_map_key(map_id, id), &[] as &[u8]);
        self.db.apply_batch(batch)?;
        self.db.flush()?;
        Ok(created_ms)
    }

    /// One stored result.
    pub fn get_localization(&self, id: u64) -> StoreResult<LocalizationRecord> {
        let key = codec::localization_key(id);
        match self.db.get(key)? {
            Some(v) => codec::decode_localization(&key, &v),
            None => Err(StoreError::LocalizationNotFound(id)),
        }
    }

    /// Up to `limit` results with ids below `before`, newest first; only `map`'s when given
    /// (which must exist).
    pub fn list_localizations(
        &self,
        map: Option<u64>,
        before: Option<u64>,
        limit: usize,
    ) -> StoreResult<Page> {
        let get = |id| self.get_localization(id);
        match map {
            Some(map) => {
                self.get_map(map)?;
                let lo = codec::by_map_key(map, 0);
                let hi = codec::by_map_key(map, before.unwrap_or(u64::MAX));
                self.page(&lo, &hi, 9, limit, get)
            }
            None => {
                let lo = codec::localization_key(0);
                let hi = codec::localization_key(before.unwrap_or(u64::MAX));
                self.page(&lo, &hi, 1, limit, get)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::test_map as map;

    #[test]
    fn lists_newest_first_with_pages() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let (a, b) = (map(&store), map(&store));
        let mut mine = Vec::new();
        for k in 0..5u8 {
            let id = store.new_localization_id().unwrap();
            store.put_localization(id, a, vec![k]).unwrap();
            mine.push(id);
            let other = store.new_localization_id().unwrap();
            store.put_localization(other, b, vec![100 + k]).unwrap();
        }
        let p1 = store.list_localizations(Some(a), None, 2).unwrap();
        let docs: Vec<u8> = p1.items.iter().map(|r| r.document[0]).collect();
        assert_eq!(docs, vec![4, 3]);
        let p2 = store.list_localizations(Some(a), p1.next, 2).unwrap();
        let p3 = store.list_localizations(Some(a), p2.next, 2).unwrap();
        assert_eq!(p3.items.len(), 1);
        assert_eq!(p3.next, None);
        assert_eq!(p3.items[0].id, mine[0]);
        let all = store.list_localizations(None, None, 100).unwrap();
        assert_eq!(all.items.len(), 10);
        assert!(all.items.windows(2).all(|w| w[0].id > w[1].id));
    }

    #[test]
    fn unknown_ids_are_reported() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        assert!(matches!(
            store.get_localization(7),
            Err(StoreError::LocalizationNotFound(7))
        ));
        assert!(matches!(
            store.list_localizations(Some(3), None, 1),
            Err(StoreError::MapNotFound(3))
        ));
        assert!(matches!(
            store.put_localization(1, 3, vec![]),
            Err(StoreError::MapNotFound(3))
        ));
    }

    #[test]
    fn deleting_a_map_deletes_its_results() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let a = map(&store);
        let id = store.new_localization_id().unwrap();
        store.put_localization(id, a, vec![1]).unwrap();
        store.delete_map(a).unwrap();
        assert!(store.get_localization(id).is_err());
        assert!(store
            .list_localizations(None, None, 10)
            .unwrap()
            .items
            .is_empty());
    }
}
