//! Maps and their reference images: create, list, get, delete, append a batch, and read
//! descriptor rows in route order.

use crate::OrStore;
use std::ops::Range;

use super::{codec, SledStore};
use seasonloc_app::model::{DescriptorSettings, ImageMeta, MapRecord};
use seasonloc_app::store::{
    append_end, now_ms, IdempotencyRecord, ImageBatch, NewMap, StoreError, StoreResult,
};
use seasonloc_core::Matrix;

impl SledStore {
    /// Creates an empty map and returns it.
    pub fn create_map(&self, new: NewMap) -> StoreResult<MapRecord> {
        let _guard = self.lock();
        if self.db()?.contains_key(codec::map_key(new.id)).or_store()? {
            return Err(StoreError::IdTaken(new.id));
        }
        let record = MapRecord {
            id: new.id,
            name: new.name,
            dim: match new.descriptor {
                DescriptorSettings::Precomputed { dim } => Some(dim),
                DescriptorSettings::Hog { .. }
                | DescriptorSettings::Cnn(_)
                | DescriptorSettings::Cooc(_) => None,
            },
            descriptor: new.descriptor,
            image_count: 0,
            created_ms: now_ms(),
        };
        let mut batch = sled::Batch::default();
        batch.insert(&codec::map_key(record.id), codec::encode_map(&record));
        self.claim_key(new.idempotency.as_ref(), None, &mut batch)?;
        self.commit(batch)?;
        Ok(record)
    }

    /// All maps, oldest first.
    pub fn list_maps(&self) -> StoreResult<Vec<MapRecord>> {
        self.db()?
            .scan_prefix([codec::MAP_PREFIX])
            .map(|kv| {
                let (k, v) = kv.or_store()?;
                codec::decode_map(&k, &v)
            })
            .collect()
    }

    /// One map.
    pub fn get_map(&self, id: u64) -> StoreResult<MapRecord> {
        let key = codec::map_key(id);
        match self.db()?.get(key).or_store()? {
            Some(v) => codec::decode_map(&key, &v),
            None => Err(StoreError::MapNotFound(id)),
        }
    }

    /// Deletes a map with its images, localizations and trips, atomically.
    pub fn delete_map(&self, id: u64) -> StoreResult<()> {
        let _guard = self.lock();
        self.get_map(id)?;
        let mut batch = sled::Batch::default();
        batch.remove(&codec::map_key(id));
        batch.remove(&codec::cooc_key(id));
        for kv in self.db()?.scan_prefix(codec::images_prefix(id)) {
            batch.remove(kv.or_store()?.0);
        }
        for kv in self.db()?.scan_prefix(codec::thumbnails_prefix(id)) {
            batch.remove(kv.or_store()?.0);
        }
        for kv in self.db()?.scan_prefix(codec::by_map_prefix(id)) {
            let (k, _) = kv.or_store()?;
            let loc = codec::id_at(&k, 9)?;
            batch.remove(&codec::localization_key(loc));
            batch.remove(&codec::picture_key(loc));
            batch.remove(k);
        }
        self.remove_trips(id, &mut batch)?;
        self.remove_keys(&IdempotencyRecord::images_scope(id), &mut batch)?;
        self.remove_creation_key(id, &mut batch)?;
        self.commit(batch)?;
        Ok(())
    }

    /// Appends one descriptor row per image (in route order) with its metadata, in one atomic,
    /// flushed write. Returns the indices given to the rows.
    ///
    /// Fails without writing anything when the map is gone or the descriptor length differs
    /// from the map's.
    pub fn append_images(&self, batch: &ImageBatch) -> StoreResult<Range<u32>> {
        let batch_in = batch;
        let (map, descriptors, metas) = (batch.map(), batch.descriptors(), batch.metas());
        let geometry = batch.geometry();
        let batch_thumbnails = batch.thumbnails();
        let _guard = self.lock();
        let mut record = self.get_map(map)?;
        if let Some(expected) = record.dim {
            if expected as usize != descriptors.cols() {
                return Err(StoreError::DimensionMismatch {
                    map,
                    expected,
                    got: descriptors.cols(),
                });
            }
        }
        let dim = u32::try_from(descriptors.cols()).map_err(|_| StoreError::DimensionMismatch {
            map,
            expected: record.dim.unwrap_or(0),
            got: descriptors.cols(),
        })?;
        let start = record.image_count;
        let end = append_end(map, start, descriptors.rows())?;
        let mut batch = sled::Batch::default();
        for (k, (row, meta)) in descriptors.iter_rows().zip(metas).enumerate() {
            let index = start + k as u32;
            batch.insert(
                &codec::image_key(map, index),
                codec::encode_image(row, meta),
            );
        }
        for (k, jpeg) in batch_thumbnails.iter().enumerate() {
            batch.insert(
                &codec::thumbnail_key(map, start + k as u32),
                jpeg.as_slice(),
            );
        }
        // A HOG map's first batch fixes its input geometry (ImageBatch::with_geometry).
        if let (None, DescriptorSettings::Hog { resize, .. }) = (record.dim, &mut record.descriptor)
        {
            *resize = resize.or(geometry);
        }
        record.dim = Some(dim);
        record.image_count = end;
        batch.insert(&codec::map_key(map), codec::encode_map(&record));
        self.claim_key(batch_in.idempotency(), Some(start..end), &mut batch)?;
        self.commit(batch)?;
        Ok(start..end)
    }

    /// Descriptor rows `rows` of a map, one per image in route order. Fails with
    /// [`StoreError::MapNotFound`] when the map is gone, and reports a missing row as corrupt.
    pub fn descriptors(&self, map: u64, rows: Range<u32>) -> StoreResult<Matrix> {
        let record = self.get_map(map)?;
        self.read_rows(&record, rows)
    }

    /// The map and all its reference descriptors, read consistently (under the write lock).
    pub fn references(&self, map: u64) -> StoreResult<(MapRecord, Matrix)> {
        let _guard = self.lock();
        let record = self.get_map(map)?;
        let matrix = self.read_rows(&record, 0..record.image_count)?;
        Ok((record, matrix))
    }

    fn read_rows(&self, record: &MapRecord, rows: Range<u32>) -> StoreResult<Matrix> {
        let map = record.id;
        let dim = record.dim.unwrap_or(0) as usize;
        let want = rows.len();
        let mut data = Vec::with_capacity(want * dim);
        let from = codec::image_key(map, rows.start);
        let to = codec::image_key(map, rows.end);
        let mut got = 0usize;
        for kv in self.db()?.range(from..to) {
            let (k, v) = kv.or_store()?;
            let before = data.len();
            codec::decode_image_into(&k, &v, &mut data)?;
            if data.len() - before != dim {
                return Err(StoreError::corrupt(
                    &k,
                    "descriptor length differs from the map's",
                ));
            }
            got += 1;
        }
        if got != want {
            // A map deleted meanwhile has no rows left; anything else is a hole.
            self.get_map(map)?;
            return Err(StoreError::corrupt(
                &codec::map_key(map),
                format!(
                    "image_count is {} but only {got} of the images {}..{} are stored",
                    record.image_count, rows.start, rows.end
                ),
            ));
        }
        Matrix::from_vec(got, dim, data).map_err(|e| StoreError::corrupt(&from, e.to_string()))
    }

    /// The JPEG thumbnail of image `index` of a map, if it has one.
    pub fn thumbnail(&self, map: u64, index: u32) -> StoreResult<Option<Vec<u8>>> {
        match self
            .db()?
            .get(codec::thumbnail_key(map, index))
            .or_store()?
        {
            Some(v) => Ok(Some(v.to_vec())),
            None => {
                self.get_map(map)?;
                Ok(None)
            }
        }
    }

    /// Metadata of the images `range` of a map, in order.
    pub fn image_metadata(&self, map: u64, range: Range<u32>) -> StoreResult<Vec<ImageMeta>> {
        self.get_map(map)?;
        let from = codec::image_key(map, range.start);
        let to = codec::image_key(map, range.end);
        let mut scratch = Vec::new();
        self.db()?
            .range(from..to)
            .map(|kv| {
                let (k, v) = kv.or_store()?;
                scratch.clear();
                codec::decode_image_into(&k, &v, &mut scratch)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hog() -> NewMap {
        NewMap {
            id: crate::test_id(),
            name: "route".into(),
            descriptor: DescriptorSettings::Hog {
                cell_size: 8,
                resize: None,
            },
            idempotency: None,
        }
    }

    fn append(
        store: &SledStore,
        map: u64,
        m: &Matrix,
        metas: &[ImageMeta],
    ) -> StoreResult<Range<u32>> {
        store.append_images(&ImageBatch::new(map, m.clone(), metas.to_vec()).unwrap())
    }

    fn rows(n: usize, dim: usize, base: f32) -> Matrix {
        Matrix::from_vec(n, dim, (0..n * dim).map(|k| base + k as f32).collect()).unwrap()
    }

    #[test]
    fn appends_keep_route_order_across_batches() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let map = store.create_map(hog()).unwrap();
        let a = append(
            &store,
            map.id,
            &rows(2, 3, 0.0),
            &[ImageMeta::default(), ImageMeta::default()],
        )
        .unwrap();
        let meta = ImageMeta {
            label: Some("bridge".into()),
            latitude: Some(63.4),
            ..ImageMeta::default()
        };
        let b = append(
            &store,
            map.id,
            &rows(1, 3, 100.0),
            std::slice::from_ref(&meta),
        )
        .unwrap();
        assert_eq!((a, b), (0..2, 2..3));
        let (record, refs) = store.references(map.id).unwrap();
        assert_eq!(record.image_count, 3);
        assert_eq!(record.dim, Some(3));
        assert_eq!(refs.row(2), &[100.0, 101.0, 102.0]);
        assert_eq!(refs.row(1), &[3.0, 4.0, 5.0]);
        assert_eq!(store.image_metadata(map.id, 2..3).unwrap(), vec![meta]);
    }

    #[test]
    fn wrong_length_writes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let map = store.create_map(hog()).unwrap();
        append(&store, map.id, &rows(1, 3, 0.0), &[ImageMeta::default()]).unwrap();
        let err = append(
            &store,
            map.id,
            &rows(2, 4, 0.0),
            &[ImageMeta::default(), ImageMeta::default()],
        )
        .unwrap_err();
        assert!(
            matches!(
                err,
                StoreError::DimensionMismatch {
                    expected: 3,
                    got: 4,
                    ..
                }
            ),
            "{err}"
        );
        assert_eq!(store.get_map(map.id).unwrap().image_count, 1);
        assert_eq!(store.references(map.id).unwrap().1.rows(), 1);
    }

    #[test]
    fn precomputed_maps_fix_their_length_at_creation() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let map = store
            .create_map(NewMap {
                id: crate::test_id(),
                name: "own".into(),
                descriptor: DescriptorSettings::Precomputed { dim: 2 },
                idempotency: None,
            })
            .unwrap();
        assert_eq!(map.dim, Some(2));
        assert!(append(&store, map.id, &rows(1, 3, 0.0), &[ImageMeta::default()]).is_err());
    }

    #[test]
    fn delete_removes_everything_and_survives_reopen() {
        let dir = tempfile::tempdir().unwrap();
        let (kept, gone) = {
            let store = SledStore::open(dir.path()).unwrap();
            let kept = store.create_map(hog()).unwrap();
            let gone = store.create_map(hog()).unwrap();
            for id in [kept.id, gone.id] {
                append(
                    &store,
                    id,
                    &rows(2, 2, 0.0),
                    &[ImageMeta::default(), ImageMeta::default()],
                )
                .unwrap();
            }
            store.delete_map(gone.id).unwrap();
            assert!(matches!(
                store.delete_map(gone.id),
                Err(StoreError::MapNotFound(_))
            ));
            (kept.id, gone.id)
        };
        let store = SledStore::open(dir.path()).unwrap();
        assert!(matches!(
            store.get_map(gone),
            Err(StoreError::MapNotFound(_))
        ));
        assert_eq!(
            store
                .db()
                .unwrap()
                .scan_prefix(codec::images_prefix(gone))
                .count(),
            0
        );
        assert_eq!(store.references(kept).unwrap().1.rows(), 2);
        assert_eq!(store.list_maps().unwrap().len(), 1);
    }

    #[test]
    fn thumbnails_ride_in_the_image_batch_and_survive_reopen() {
        let dir = tempfile::tempdir().unwrap();
        let metas = [ImageMeta::default(), ImageMeta::default()];
        let map = {
            let store = SledStore::open(dir.path()).unwrap();
            let map = store.create_map(hog()).unwrap();
            // Images without thumbnails (precomputed-style batch) have none.
            append(&store, map.id, &rows(2, 3, 0.0), &metas).unwrap();
            let with = ImageBatch::new(map.id, rows(2, 3, 9.0), metas.to_vec())
                .unwrap()
                .with_thumbnails(vec![b"jpeg-2".to_vec(), b"jpeg-3".to_vec()])
                .unwrap();
            assert_eq!(store.append_images(&with).unwrap(), 2..4);
            // A refused batch writes neither its rows nor its thumbnails.
            let wrong = ImageBatch::new(map.id, rows(1, 4, 0.0), metas[..1].to_vec())
                .unwrap()
                .with_thumbnails(vec![b"never".to_vec()])
                .unwrap();
            assert!(store.append_images(&wrong).is_err());
            // The count must match the rows.
            assert!(ImageBatch::new(map.id, rows(2, 3, 0.0), metas.to_vec())
                .unwrap()
                .with_thumbnails(vec![b"one".to_vec()])
                .is_err());
            map.id
            // Dropped without a clean shutdown: what `append_images` acknowledged was flushed.
        };
        let store = SledStore::open(dir.path()).unwrap();
        assert_eq!(store.thumbnail(map, 0).unwrap(), None);
        assert_eq!(store.thumbnail(map, 2).unwrap(), Some(b"jpeg-2".to_vec()));
        assert_eq!(store.thumbnail(map, 3).unwrap(), Some(b"jpeg-3".to_vec()));
        assert_eq!(store.thumbnail(map, 4).unwrap(), None);
        assert!(matches!(
            store.thumbnail(map + 1, 0),
            Err(StoreError::MapNotFound(_))
        ));
        store.delete_map(map).unwrap();
        assert_eq!(
            store
                .db()
                .unwrap()
                .scan_prefix(codec::thumbnails_prefix(map))
                .count(),
            0
        );
    }

    #[test]
    fn maps_keep_the_callers_id_and_a_taken_id_writes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(dir.path()).unwrap();
        let b = store
            .create_map(NewMap {
                id: 0x00c0_ffee_0000_0002,
                ..hog()
            })
            .unwrap();
        let a = store.create_map(NewMap { id: 7, ..hog() }).unwrap();
        assert_eq!((a.id, b.id), (7, 0x00c0_ffee_0000_0002));
        let again = store.create_map(NewMap {
            id: 7,
            name: "other".into(),
            ..hog()
        });
        assert!(matches!(again, Err(StoreError::IdTaken(7))), "{again:?}");
        assert_eq!(store.get_map(7).unwrap().name, "route");
        // Listed oldest (smallest id) first.
        let listed: Vec<u64> = store.list_maps().unwrap().iter().map(|m| m.id).collect();
        assert_eq!(listed, vec![a.id, b.id]);
    }
}
