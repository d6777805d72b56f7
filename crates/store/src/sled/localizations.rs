//! Stored localization results: create (a new id), get, and list (all or by map, newest
//! first, paginated by an exclusive `before` id).

use super::{codec, SledStore};
use crate::OrStore;
use seasonloc_app::model::LocalizationRecord;
use seasonloc_app::store::{now_ms, NewLocalization, Page, PageRequest, StoreError, StoreResult};

impl SledStore {
    /// Stores a result for its map under a new id, atomically with its index entry, flushed.
    /// Fails with [`StoreError::MapNotFound`] when the map is gone.
    pub fn create_localization(&self, new: NewLocalization) -> StoreResult<LocalizationRecord> {
        let _guard = self.lock();
        self.get_map(new.map_id)?;
        let id = new.id;
        if self
            .db()?
            .contains_key(codec::localization_key(id))
            .or_store()?
        {
            return Err(StoreError::IdTaken(id));
        }
        let created_ms = now_ms();
        let record = LocalizationRecord {
            id,
            map_id: new.map_id,
            created_ms,
            result: new.result,
        };
        let mut batch = sled::Batch::default();
        batch.insert(
            &codec::localization_key(id),
            codec::encode_localization(&record)?,
        );
        batch.insert(&codec::by_map_key(record.map_id, id), &[] as &[u8]);
        if let Some(png) = &new.picture {
            batch.insert(&codec::picture_key(id), png.as_slice());
        }
        self.claim_key(new.idempotency.as_ref(), None, &mut batch)?;
        self.commit(batch)?;
        Ok(record)
    }

    /// One stored result.
    pub fn get_localization(&self, id: u64) -> StoreResult<LocalizationRecord> {
        let key = codec::localization_key(id);
        match self.db()?.get(key).or_store()? {
            Some(v) => codec::decode_localization(&key, &v),
            None => Err(StoreError::LocalizationNotFound(id)),
        }
    }

    /// The PNG of a stored result's similarity picture, if it has one.
    pub fn localization_picture(&self, id: u64) -> StoreResult<Option<Vec<u8>>> {
        match self.db()?.get(codec::picture_key(id)).or_store()? {
            Some(v) => Ok(Some(v.to_vec())),
            None => {
                self.get_localization(id)?;
                Ok(None)
            }
        }
    }

    /// A page of results, newest first; only `map`'s when given (which must exist).
    pub fn list_localizations(
        &self,
        map: Option<u64>,
        page: PageRequest,
    ) -> StoreResult<Page<LocalizationRecord>> {
        let get = |id| self.get_localization(id);
        let before = page.before.unwrap_or(u64::MAX);
        match map {
            Some(map) => {
                self.get_map(map)?;
                let lo = codec::by_map_key(map, 0);
                let hi = codec::by_map_key(map, before);
                self.page(&lo, &hi, 9, page.limit, get)
            }
            None => {
                let lo = codec::localization_key(0);
                let hi = codec::localization_key(before);
                self.page(&lo, &hi, 1, page.limit, get)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sled::test_map as map;
    use seasonloc_app::model::{LocalizationParams, LocalizationResult, LocalizationTimings};

    /// A result whose `query_count` tells results apart.
    fn result(k: u8) -> LocalizationResult {
        LocalizationResult {
            query_count: usize::from(k),
            reference_count: 1,
            params: LocalizationParams::new(
                &seasonloc_core::localize::LocalizeOptions::default(),
                1.0,
                None,
            ),
            total_cost: 0.0,
            hypotheses: Vec::new(),
            predictions: Vec::new(),
            timings: LocalizationTimings::default(),
            picture: None,
        }
    }

    fn put(store: &SledStore, map_id: u64, k: u8) -> StoreResult<LocalizationRecord> {
        store.create_localization(NewLocalization {
            id: crate::test_id(),
            map_id,
            result: result(k),
            picture: None,
            idempotency: None,
        })
    }

    fn page(before: Option<u64>, limit: usize) -> PageRequest {
        PageRequest { before, limit }
    }

    #[test]
    fn lists_newest_first_with_pages() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let (a, b) = (map(&store), map(&store));
        let mut mine = Vec::new();
        for k in 0..5u8 {
            mine.push(put(&store, a, k).unwrap().id);
            put(&store, b, 100 + k).unwrap();
        }
        let p1 = store.list_localizations(Some(a), page(None, 2)).unwrap();
        let docs: Vec<u8> = p1
            .items
            .iter()
            .map(|r| r.result.query_count as u8)
            .collect();
        assert_eq!(docs, vec![4, 3]);
        let p2 = store.list_localizations(Some(a), page(p1.next, 2)).unwrap();
        let p3 = store.list_localizations(Some(a), page(p2.next, 2)).unwrap();
        assert_eq!(p3.items.len(), 1);
        assert_eq!(p3.next, None);
        assert_eq!(p3.items[0].id, mine[0]);
        let all = store.list_localizations(None, page(None, 100)).unwrap();
        assert_eq!(all.items.len(), 10);
        assert!(all.items.windows(2).all(|w| w[0].id > w[1].id));
    }

    #[test]
    fn the_document_carries_the_record_identity() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let a = map(&store);
        let r = put(&store, a, 7).unwrap();
        // The stored document itself names the record: its id, map and creation time.
        let raw = store
            .db()
            .unwrap()
            .get(codec::localization_key(r.id))
            .unwrap()
            .unwrap();
        let doc = crate::document::localization_from_json(b"L", &raw[1 + 8 + 8 + 8 + 4..]).unwrap();
        assert_eq!(
            (doc.id, doc.map_id, doc.created_ms),
            (r.id, a, r.created_ms)
        );
        assert_eq!(store.get_localization(r.id).unwrap(), r);
    }

    #[test]
    fn unknown_ids_are_reported() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        assert!(matches!(
            store.get_localization(7),
            Err(StoreError::LocalizationNotFound(7))
        ));
        assert!(matches!(
            store.list_localizations(Some(3), page(None, 1)),
            Err(StoreError::MapNotFound(3))
        ));
        assert!(matches!(put(&store, 3, 0), Err(StoreError::MapNotFound(3))));
    }

    #[test]
    fn deleting_a_map_deletes_its_results() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let a = map(&store);
        let id = put(&store, a, 1).unwrap().id;
        store.delete_map(a).unwrap();
        assert!(store.get_localization(id).is_err());
        assert!(store
            .list_localizations(None, page(None, 10))
            .unwrap()
            .items
            .is_empty());
    }
}
