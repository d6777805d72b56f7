//! Maps, their reference images and co-occurrence models on PostgreSQL.
//!
//! A batch of images is one `image_batches` row (descriptors as raw little-endian `f32`, one
//! encoded metadata record per image), inserted in the transaction that raises the map's
//! `image_count` with the map row locked (`FOR UPDATE`), so concurrent appends from several
//! replicas get consecutive, non-overlapping indices. Reading rows `a..b` reads the batches
//! that overlap them and slices.

use crate::OrStore;
use std::ops::Range;

use tokio_postgres::error::SqlState;
use tokio_postgres::Row;

use super::{corrupt, db_id, small, unsigned, PgStore};
use crate::sled::codec;
use seasonloc_app::model::{DescriptorSettings, ImageMeta, MapRecord};
use seasonloc_app::store::{
    append_end, now_ms, CoocWrite, ImageBatch, NewMap, StoreError, StoreResult,
};
use seasonloc_core::Matrix;

const MAP_COLUMNS: &str = "id, name, settings, dim, image_count, created_ms";

/// A `maps` row as a record (the settings decoded, the columns authoritative).
fn map_from_row(row: &Row) -> StoreResult<MapRecord> {
    let id: i64 = row.get(0);
    let settings: &[u8] = row.get(2);
    let decoded = codec::decode_map(format!("maps/{id}").as_bytes(), settings)?;
    let dim: Option<i64> = row.get(3);
    Ok(MapRecord {
        id: unsigned("maps", id, id)?,
        name: row.get(1),
        descriptor: decoded.descriptor,
        dim: dim.map(|d| small("maps", id, d)).transpose()?,
        image_count: small("maps", id, row.get(4))?,
        created_ms: unsigned("maps", id, row.get(5))?,
    })
}

/// Little-endian bytes of `values`.
fn f32_bytes(values: &[f32]) -> Vec<u8> {
    let mut out = Vec::with_capacity(values.len() * 4);
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Appends the `f32`s of little-endian `bytes` to `out`.
fn extend_f32(out: &mut Vec<f32>, bytes: &[u8]) {
    out.extend(
        bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])),
    );
}

/// One stored batch overlapping a requested range.
struct BatchRow {
    first: u32,
    count: u32,
    dim: usize,
    descriptors: Vec<u8>,
    metas: Vec<Vec<u8>>,
}

impl BatchRow {
    fn from_row(map: i64, row: &Row) -> StoreResult<BatchRow> {
        let first = small("image_batches", map, row.get(0))?;
        let count = small("image_batches", map, row.get(1))?;
        let dim = small("image_batches", map, row.get(2))? as usize;
        let descriptors: Vec<u8> = row.get(3);
        let metas: Vec<Vec<u8>> = row.get(4);
        if descriptors.len() != count as usize * dim * 4 || metas.len() != count as usize {
            return Err(corrupt(
                "image_batches",
                map,
                format!("batch at {first} does not hold {count} images of length {dim}"),
            ));
        }
        Ok(BatchRow {
            first,
            count,
            dim,
            descriptors,
            metas,
        })
    }

    /// The part of this batch inside `rows`, as indices into the batch.
    fn overlap(&self, rows: &Range<u32>) -> Range<usize> {
        let lo = rows.start.max(self.first);
        let hi = rows.end.min(self.first + self.count);
        (lo.saturating_sub(self.first) as usize)..(hi.saturating_sub(self.first) as usize)
    }
}

impl PgStore {
    pub(super) async fn insert_map(&self, new: NewMap) -> StoreResult<MapRecord> {
        let dim = match new.descriptor {
            DescriptorSettings::Precomputed { dim } => Some(dim),
            DescriptorSettings::Hog { .. }
            | DescriptorSettings::Cnn(_)
            | DescriptorSettings::Cooc(_) => None,
        };
        let key = db_id(new.id).ok_or(StoreError::IdTaken(new.id))?;
        let created_ms = now_ms();
        // Only the settings of this encoding are read back (see the schema).
        let settings = codec::encode_map(&MapRecord {
            id: 0,
            name: String::new(),
            descriptor: new.descriptor.clone(),
            dim: None,
            image_count: 0,
            created_ms: 0,
        });
        let mut client = self.client().await?;
        // One transaction: the map and, for a keyed request, its idempotency record.
        let tx = client.transaction().await.or_store()?;
        let stmt = tx
            .prepare_cached(
                "INSERT INTO maps (id, name, settings, dim, image_count, created_ms)
                 VALUES ($5, $1, $2, $3, 0, $4) RETURNING id",
            )
            .await
            .or_store()?;
        let row = tx
            .query_one(
                &stmt,
                &[
                    &new.name,
                    &settings,
                    &dim.map(i64::from),
                    &i64::try_from(created_ms).unwrap_or(i64::MAX),
                    &key,
                ],
            )
            .await
            .map_err(|e| {
                if is_duplicate(&e) {
                    StoreError::IdTaken(new.id)
                } else {
                    super::db_error(e)
                }
            })?;
        let id: i64 = row.get(0);
        PgStore::claim_key(&tx, id, new.idempotency.as_ref(), None).await?;
        tx.commit().await.or_store()?;
        Ok(MapRecord {
            id: unsigned("maps", id, id)?,
            name: new.name,
            descriptor: new.descriptor,
            dim,
            image_count: 0,
            created_ms,
        })
    }

    pub(super) async fn map(&self, id: u64) -> StoreResult<MapRecord> {
        let key = db_id(id).ok_or(StoreError::MapNotFound(id))?;
        let client = self.client().await?;
        let stmt = client
            .prepare_cached(&format!("SELECT {MAP_COLUMNS} FROM maps WHERE id = $1"))
            .await
            .or_store()?;
        match client.query_opt(&stmt, &[&key]).await.or_store()? {
            Some(row) => map_from_row(&row),
            None => Err(StoreError::MapNotFound(id)),
        }
    }

    pub(super) async fn all_maps(&self) -> StoreResult<Vec<MapRecord>> {
        let client = self.client().await?;
        let stmt = client
            .prepare_cached(&format!("SELECT {MAP_COLUMNS} FROM maps ORDER BY id"))
            .await
            .or_store()?;
        client
            .query(&stmt, &[])
            .await
            .or_store()?
            .iter()
            .map(map_from_row)
            .collect()
    }

    pub(super) async fn remove_map(&self, id: u64) -> StoreResult<()> {
        let key = db_id(id).ok_or(StoreError::MapNotFound(id))?;
        let client = self.client().await?;
        let stmt = client
            .prepare_cached("DELETE FROM maps WHERE id = $1")
            .await
            .or_store()?;
        match client.execute(&stmt, &[&key]).await.or_store()? {
            0 => Err(StoreError::MapNotFound(id)),
            _ => Ok(()),
        }
    }

    pub(super) async fn append(&self, batch: ImageBatch) -> StoreResult<Range<u32>> {
        let map = batch.map();
        let key = db_id(map).ok_or(StoreError::MapNotFound(map))?;
        let descriptors = batch.descriptors();
        let cols = descriptors.cols();
        let bytes = f32_bytes(descriptors.as_slice());
        let metas: Vec<Vec<u8>> = batch
            .metas()
            .iter()
            .map(|m| codec::encode_image(&[], m))
            .collect();
        // NULL, not an empty array, for a batch without thumbnails (see migration 0003).
        let thumbnails: Option<&[Vec<u8>]> = Some(batch.thumbnails()).filter(|t| !t.is_empty());
        let mut client = self.client().await?;
        let tx = client.transaction().await.or_store()?;
        let row = lock_map(
            &tx,
            "SELECT dim, image_count, settings FROM maps WHERE id = $1 FOR UPDATE",
            key,
            map,
        )
        .await?;
        let stored_dim: Option<i64> = row.get(0);
        let start = small("maps", key, row.get(1))?;
        // A HOG map's first batch fixes its input geometry (ImageBatch::with_geometry), in
        // this transaction: the settings to write back, if they change.
        let settings = match (stored_dim, batch.geometry()) {
            (None, Some(geometry)) => {
                let stored: &[u8] = row.get(2);
                let mut record = codec::decode_map(format!("maps/{key}").as_bytes(), stored)?;
                match &mut record.descriptor {
                    DescriptorSettings::Hog { resize, .. } if resize.is_none() => {
                        *resize = Some(geometry);
                        Some(codec::encode_map(&record))
                    }
                    DescriptorSettings::Hog { .. }
                    | DescriptorSettings::Precomputed { .. }
                    | DescriptorSettings::Cnn(_)
                    | DescriptorSettings::Cooc(_) => None,
                }
            }
            (None, None) | (Some(_), _) => None,
        };
        if let Some(expected) = stored_dim {
            if expected != cols as i64 {
                return Err(StoreError::DimensionMismatch {
                    map,
                    expected: small("maps", key, expected)?,
                    got: cols,
                });
            }
        }
        let dim = u32::try_from(cols).map_err(|_| StoreError::DimensionMismatch {
            map,
            expected: 0,
            got: cols,
        })?;
        let end = append_end(map, start, descriptors.rows())?;
        if end > start {
            let insert = tx
                .prepare_cached(
                    "INSERT INTO image_batches
                         (map_id, first, count, dim, descriptors, metas, thumbnails)
                     VALUES ($1, $2, $3, $4, $5, $6, $7)",
                )
                .await
                .or_store()?;
            tx.execute(
                &insert,
                &[
                    &key,
                    &i64::from(start),
                    &i64::from(end - start),
                    &i64::from(dim),
                    &bytes,
                    &metas,
                    &thumbnails,
                ],
            )
            .await
            .or_store()?;
        }
        let update = tx
            .prepare_cached(
                "UPDATE maps SET dim = $2, image_count = $3, settings = coalesce($4, settings)
                 WHERE id = $1",
            )
            .await
            .or_store()?;
        tx.execute(
            &update,
            &[&key, &Some(i64::from(dim)), &i64::from(end), &settings],
        )
        .await
        .or_store()?;
        PgStore::claim_key(&tx, key, batch.idempotency(), Some(start..end)).await?;
        tx.commit().await.or_store()?;
        Ok(start..end)
    }

    /// The batches of `map` overlapping `rows`, after checking that the map exists and holds
    /// them; also the map's descriptor length.
    async fn batches(&self, map: u64, rows: &Range<u32>) -> StoreResult<(usize, Vec<BatchRow>)> {
        let key = db_id(map).ok_or(StoreError::MapNotFound(map))?;
        let client = self.client().await?;
        let head = client
            .prepare_cached("SELECT dim, image_count FROM maps WHERE id = $1")
            .await
            .or_store()?;
        let row = client
            .query_opt(&head, &[&key])
            .await
            .or_store()?
            .ok_or(StoreError::MapNotFound(map))?;
        let dim: Option<i64> = row.get(0);
        let dim = dim.map_or(Ok(0), |d| small("maps", key, d))? as usize;
        let count = small("maps", key, row.get(1))?;
        if rows.end > count {
            return Err(corrupt(
                "maps",
                key,
                format!(
                    "images {}..{} asked for, the map has {count}",
                    rows.start, rows.end
                ),
            ));
        }
        if rows.is_empty() {
            return Ok((dim, Vec::new()));
        }
        let stmt = client
            .prepare_cached(
                "SELECT first, count, dim, descriptors, metas FROM image_batches
                 WHERE map_id = $1 AND first < $3 AND first + count > $2 ORDER BY first",
            )
            .await
            .or_store()?;
        let batches = client
            .query(&stmt, &[&key, &i64::from(rows.start), &i64::from(rows.end)])
            .await
            .or_store()?
            .iter()
            .map(|r| BatchRow::from_row(key, r))
            .collect::<StoreResult<Vec<_>>>()?;
        // The overlapping batches must tile the range exactly.
        let mut next = rows.start;
        for b in &batches {
            let part = b.overlap(rows);
            if b.first.max(rows.start) != next || part.is_empty() {
                break;
            }
            next = b.first + part.end as u32;
        }
        if next != rows.end {
            // A map deleted meanwhile has no batches left; anything else is a hole.
            if client.query_opt(&head, &[&key]).await.or_store()?.is_none() {
                return Err(StoreError::MapNotFound(map));
            }
            return Err(corrupt(
                "image_batches",
                key,
                format!(
                    "images {}..{} are not all stored (stopped at {next})",
                    rows.start, rows.end
                ),
            ));
        }
        Ok((dim, batches))
    }

    pub(super) async fn rows(&self, map: u64, rows: Range<u32>) -> StoreResult<Matrix> {
        let (dim, batches) = self.batches(map, &rows).await?;
        let mut data = Vec::with_capacity(rows.len() * dim);
        for b in &batches {
            if b.dim != dim {
                return Err(corrupt(
                    "image_batches",
                    db_id(map).unwrap_or(0),
                    format!("batch at {} has length {}, the map {dim}", b.first, b.dim),
                ));
            }
            let part = b.overlap(&rows);
            extend_f32(
                &mut data,
                &b.descriptors[part.start * dim * 4..part.end * dim * 4],
            );
        }
        Matrix::from_vec(rows.len(), dim, data)
            .map_err(|e| corrupt("image_batches", db_id(map).unwrap_or(0), e.to_string()))
    }

    pub(super) async fn metas(&self, map: u64, rows: Range<u32>) -> StoreResult<Vec<ImageMeta>> {
        let (_, batches) = self.batches(map, &rows).await?;
        let mut out = Vec::with_capacity(rows.len());
        let mut scratch = Vec::new();
        for b in &batches {
            for (k, encoded) in b.metas[b.overlap(&rows)].iter().enumerate() {
                let name = format!("image_batches/{map}/{}", b.first as usize + k);
                scratch.clear();
                out.push(codec::decode_image_into(
                    name.as_bytes(),
                    encoded,
                    &mut scratch,
                )?);
            }
        }
        Ok(out)
    }

    pub(super) async fn thumbnail_of(&self, map: u64, index: u32) -> StoreResult<Option<Vec<u8>>> {
        let key = db_id(map).ok_or(StoreError::MapNotFound(map))?;
        let client = self.client().await?;
        // The map row decides "gone" vs "no thumbnail"; the batch holding `index`, if any, its
        // thumbnail (PostgreSQL arrays count from 1; out of range or NULL array: NULL).
        let stmt = client
            .prepare_cached(
                "SELECT b.thumbnails[$2 - b.first + 1]
                 FROM maps m LEFT JOIN image_batches b
                   ON b.map_id = m.id AND b.first <= $2 AND b.first + b.count > $2
                 WHERE m.id = $1",
            )
            .await
            .or_store()?;
        match client
            .query_opt(&stmt, &[&key, &i64::from(index)])
            .await
            .or_store()?
        {
            Some(row) => Ok(row.get(0)),
            None => Err(StoreError::MapNotFound(map)),
        }
    }

    pub(super) async fn cooc(&self, map: u64) -> StoreResult<Option<Vec<u8>>> {
        let key = db_id(map).ok_or(StoreError::MapNotFound(map))?;
        let client = self.client().await?;
        let stmt = client
            .prepare_cached(
                "SELECT c.encoded FROM maps m LEFT JOIN cooc_maps c ON c.map_id = m.id
                 WHERE m.id = $1",
            )
            .await
            .or_store()?;
        match client.query_opt(&stmt, &[&key]).await.or_store()? {
            Some(row) => Ok(row.get(0)),
            None => Err(StoreError::MapNotFound(map)),
        }
    }

    pub(super) async fn replace_cooc(&self, write: CoocWrite) -> StoreResult<Range<u32>> {
        let CoocWrite {
            map,
            previous,
            encoded,
            new_images,
            idempotency,
        } = write;
        let key = db_id(map).ok_or(StoreError::MapNotFound(map))?;
        let metas: Vec<Vec<u8>> = new_images
            .iter()
            .map(|m| codec::encode_image(&[], m))
            .collect();
        let mut client = self.client().await?;
        let tx = client.transaction().await.or_store()?;
        let row = lock_map(
            &tx,
            "SELECT image_count FROM maps WHERE id = $1 FOR UPDATE",
            key,
            map,
        )
        .await?;
        let start = small("maps", key, row.get(0))?;
        let current = tx
            .prepare_cached("SELECT encoded FROM cooc_maps WHERE map_id = $1")
            .await
            .or_store()?;
        let stored: Option<Vec<u8>> = tx
            .query_opt(&current, &[&key])
            .await
            .or_store()?
            .map(|r| r.get(0));
        if stored != previous {
            return Err(StoreError::Conflict(map));
        }
        let end = append_end(map, start, metas.len())?;
        if end > start {
            let insert = tx
                .prepare_cached(
                    "INSERT INTO image_batches (map_id, first, count, dim, descriptors, metas)
                     VALUES ($1, $2, $3, 0, ''::bytea, $4)",
                )
                .await
                .or_store()?;
            tx.execute(
                &insert,
                &[&key, &i64::from(start), &i64::from(end - start), &metas],
            )
            .await
            .or_store()?;
        }
        let upsert = tx
            .prepare_cached(
                "INSERT INTO cooc_maps (map_id, encoded) VALUES ($1, $2)
                 ON CONFLICT (map_id) DO UPDATE SET encoded = EXCLUDED.encoded",
            )
            .await
            .or_store()?;
        tx.execute(&upsert, &[&key, &encoded]).await.or_store()?;
        let update = tx
            .prepare_cached("UPDATE maps SET image_count = $2 WHERE id = $1")
            .await
            .or_store()?;
        tx.execute(&update, &[&key, &i64::from(end)])
            .await
            .or_store()?;
        PgStore::claim_key(&tx, key, idempotency.as_ref(), Some(start..end)).await?;
        tx.commit().await.or_store()?;
        Ok(start..end)
    }
}

/// `map`'s row read by `select` (a `SELECT ... FROM maps WHERE id = $1 FOR UPDATE`), locked
/// until `tx` ends: where concurrent appends to one map queue up.
async fn lock_map(
    tx: &deadpool_postgres::Transaction<'_>,
    select: &str,
    key: i64,
    map: u64,
) -> StoreResult<Row> {
    let lock = tx.prepare_cached(select).await.or_store()?;
    tx.query_opt(&lock, &[&key])
        .await
        .or_store()?
        .ok_or(StoreError::MapNotFound(map))
}

/// Whether a database error is a primary-key violation (the id is taken).
pub(super) fn is_duplicate(e: &tokio_postgres::Error) -> bool {
    e.code() == Some(&SqlState::UNIQUE_VIOLATION)
}

/// Whether a database error is a foreign-key violation (the parent row is gone).
pub(super) fn is_missing_parent(e: &tokio_postgres::Error) -> bool {
    e.code() == Some(&SqlState::FOREIGN_KEY_VIOLATION)
}
