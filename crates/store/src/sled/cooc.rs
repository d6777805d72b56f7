//! Storage of `cooc` maps: the encoded `CoocMap` (vocabulary, drives, quantised features) under
//! `C` + map id, written together with the map record (and the metadata records of new
//! reference images) in one atomic, flushed batch.
//!
//! The store treats the encoding as opaque bytes. Writers read the current bytes, compute the
//! new map outside the write lock (seconds of CPU), and write back only if the stored bytes are
//! still the ones they started from ([`StoreError::Conflict`] otherwise), so two concurrent
//! drives never silently lose one another.

use crate::OrStore;
use std::ops::Range;

use super::{codec, SledStore};
use seasonloc_app::store::{append_end, CoocWrite, StoreError, StoreResult};

impl SledStore {
    /// The encoded co-occurrence map of `map`, `None` before its first images.
    pub fn cooc_map(&self, map: u64) -> StoreResult<Option<Vec<u8>>> {
        self.get_map(map)?;
        Ok(self
            .db()?
            .get(codec::cooc_key(map))
            .or_store()?
            .map(|v| v.to_vec()))
    }

    /// Replaces the encoded co-occurrence map of `write.map` by `write.encoded` if the stored
    /// one still equals `write.previous` (`None` = none yet), and appends one (descriptor-less)
    /// image record per entry of `write.new_images`; one atomic, flushed batch. Returns the
    /// indices of the new images.
    pub fn put_cooc_map(&self, write: CoocWrite) -> StoreResult<Range<u32>> {
        let CoocWrite {
            map,
            previous,
            encoded,
            new_images,
            idempotency,
        } = write;
        let previous = previous.as_deref();
        let _guard = self.lock();
        let mut record = self.get_map(map)?;
        let current = self.db()?.get(codec::cooc_key(map)).or_store()?;
        if current.as_deref() != previous {
            return Err(StoreError::Conflict(map));
        }
        let start = record.image_count;
        let end = append_end(map, start, new_images.len())?;
        let mut batch = sled::Batch::default();
        for (k, meta) in new_images.iter().enumerate() {
            let index = start + k as u32;
            batch.insert(
                &codec::image_key(map, index),
                codec::encode_image(&[], meta),
            );
        }
        record.image_count = end;
        batch.insert(&codec::map_key(map), codec::encode_map(&record));
        batch.insert(&codec::cooc_key(map), encoded);
        self.claim_key(idempotency.as_ref(), Some(start..end), &mut batch)?;
        self.commit(batch)?;
        Ok(start..end)
    }
}

#[cfg(test)]
mod tests {
    use crate::sled::SledStore;
    use seasonloc_app::model::{DescriptorSettings, ImageMeta};
    use seasonloc_app::store::{CoocWrite, NewMap, StoreError};

    fn write(map: u64, previous: Option<&[u8]>, encoded: &[u8], n: usize) -> CoocWrite {
        CoocWrite {
            map,
            previous: previous.map(<[u8]>::to_vec),
            encoded: encoded.to_vec(),
            new_images: vec![ImageMeta::default(); n],
            idempotency: None,
        }
    }

    #[test]
    fn cooc_maps_are_replaced_only_from_the_version_read() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let m = store
            .create_map(NewMap {
                id: crate::test_id(),
                name: "c".into(),
                descriptor: DescriptorSettings::Cooc(Box::default()),
                idempotency: None,
            })
            .unwrap();
        assert_eq!(store.cooc_map(m.id).unwrap(), None);
        assert_eq!(
            store.put_cooc_map(write(m.id, None, b"v1", 3)).unwrap(),
            0..3
        );
        // A writer that started from "no map" lost the race: nothing is written.
        assert!(matches!(
            store.put_cooc_map(write(m.id, None, b"v1'", 0)),
            Err(StoreError::Conflict(_))
        ));
        assert_eq!(
            store
                .put_cooc_map(write(m.id, Some(b"v1"), b"v2", 0))
                .unwrap(),
            3..3
        );
        drop(store);
        let store = SledStore::open(dir.path()).unwrap();
        assert_eq!(store.cooc_map(m.id).unwrap().as_deref(), Some(&b"v2"[..]));
        assert_eq!(store.get_map(m.id).unwrap().image_count, 3);
        store.delete_map(m.id).unwrap();
        assert!(store.cooc_map(m.id).is_err());
    }
}
