//! Localization results and trips on PostgreSQL.
//!
//! A trip's state is its `base` and `snapshot` columns and its `trip_log` rows (or, for a trip
//! written by schema 1-3, the `state` blob), read in one statement. A trip batch is one
//! transaction: a conditional `UPDATE` of the trip row (open, and still at
//! the frame count the batch was computed after) that writes the new record fields and solver
//! state, then an upsert of the batch's estimates. When the `UPDATE` matches no row nothing is
//! written and the trip is read again to say why (gone, closed, or moved on), so of two
//! replicas racing with batches computed from one state exactly one applies.

use crate::OrStore;
use tokio_postgres::Row;

use super::maps::{is_duplicate, is_missing_parent};
use super::{before, corrupt, db_id, fetch, paged, small, unsigned, PgStore};
use crate::document;
use seasonloc_app::model::{LocalizationRecord, TripRecord};
use seasonloc_app::store::{
    now_ms, NewLocalization, NewTrip, Page, PageRequest, StoreError, StoreResult, TripBatch,
    TripState,
};
use seasonloc_core::calibration::FrameStatus;
use seasonloc_core::trip::{FrameEstimate, TripStatus};

/// The stored code of a trip status (0: no batch yet).
fn status_code(s: Option<TripStatus>) -> i16 {
    match s {
        None => 0,
        Some(TripStatus::Localized) => 1,
        Some(TripStatus::Lost) => 2,
        Some(TripStatus::Relocalized) => 3,
    }
}

fn status_of(id: i64, code: i16) -> StoreResult<Option<TripStatus>> {
    match code {
        0 => Ok(None),
        1 => Ok(Some(TripStatus::Localized)),
        2 => Ok(Some(TripStatus::Lost)),
        3 => Ok(Some(TripStatus::Relocalized)),
        c => Err(corrupt("trips", id, format!("unknown trip status {c}"))),
    }
}

fn ms(value: u64) -> i64 {
    i64::try_from(value).unwrap_or(i64::MAX)
}

const TRIP_COLUMNS: &str =
    "id, map_id, created_ms, closed_ms, frame_count, reference_count, status, params, owner";

/// A `trips` row (the first nine columns [`TRIP_COLUMNS`]) as a record.
fn trip_from_row(row: &Row) -> StoreResult<TripRecord> {
    let id: i64 = row.get(0);
    let closed: Option<i64> = row.get(3);
    let params: &[u8] = row.get(7);
    Ok(TripRecord {
        id: unsigned("trips", id, id)?,
        map_id: unsigned("trips", id, row.get(1))?,
        created_ms: unsigned("trips", id, row.get(2))?,
        closed_ms: closed.map(|c| unsigned("trips", id, c)).transpose()?,
        frame_count: unsigned("trips", id, row.get(4))?,
        reference_count: small("trips", id, row.get(5))?,
        status: status_of(id, row.get(6))?,
        params: document::trip_params_from_json(format!("trips/{id}").as_bytes(), params)?,
        owner: row.get(8),
    })
}

/// A `localizations` row (id, map_id, created_ms, document) as a record.
fn localization_from_row(row: &Row) -> StoreResult<LocalizationRecord> {
    let id: i64 = row.get(0);
    let document: &[u8] = row.get(3);
    document::localization_checked(
        format!("localizations/{id}").as_bytes(),
        document,
        unsigned("localizations", id, id)?,
        unsigned("localizations", id, row.get(1))?,
    )
}

impl PgStore {
    /// Fails with [`StoreError::MapNotFound`] unless the map exists.
    async fn require_map(&self, client: &tokio_postgres::Client, map: u64) -> StoreResult<i64> {
        let key = db_id(map).ok_or(StoreError::MapNotFound(map))?;
        let exists = client
            .query_opt("SELECT 1 FROM maps WHERE id = $1", &[&key])
            .await
            .or_store()?;
        exists.map(|_| key).ok_or(StoreError::MapNotFound(map))
    }

    pub(super) async fn insert_localization(
        &self,
        new: NewLocalization,
    ) -> StoreResult<LocalizationRecord> {
        let map = db_id(new.map_id).ok_or(StoreError::MapNotFound(new.map_id))?;
        let id = db_id(new.id).ok_or(StoreError::IdTaken(new.id))?;
        let mut client = self.client().await?;
        let created_ms = now_ms();
        let record = LocalizationRecord {
            id: unsigned("localizations", id, id)?,
            map_id: new.map_id,
            created_ms,
            result: new.result,
        };
        let json = document::localization_json(&record)?;
        // One transaction: the result and, for a keyed request, its idempotency record.
        let tx = client.transaction().await.or_store()?;
        let stmt = tx
            .prepare_cached(
                "INSERT INTO localizations (id, map_id, created_ms, document, picture)
                 VALUES ($1, $2, $3, $4, $5)",
            )
            .await
            .or_store()?;
        match tx
            .execute(&stmt, &[&id, &map, &ms(created_ms), &json, &new.picture])
            .await
        {
            Ok(_) => {}
            Err(e) if is_missing_parent(&e) => return Err(StoreError::MapNotFound(new.map_id)),
            Err(e) if is_duplicate(&e) => return Err(StoreError::IdTaken(new.id)),
            Err(e) => return Err(super::db_error(e)),
        }
        PgStore::claim_key(&tx, map, new.idempotency.as_ref(), None).await?;
        tx.commit().await.or_store()?;
        Ok(record)
    }

    pub(super) async fn localization(&self, id: u64) -> StoreResult<LocalizationRecord> {
        let key = db_id(id).ok_or(StoreError::LocalizationNotFound(id))?;
        let client = self.client().await?;
        let stmt = client
            .prepare_cached(
                "SELECT id, map_id, created_ms, document FROM localizations WHERE id = $1",
            )
            .await
            .or_store()?;
        match client.query_opt(&stmt, &[&key]).await.or_store()? {
            Some(row) => localization_from_row(&row),
            None => Err(StoreError::LocalizationNotFound(id)),
        }
    }

    pub(super) async fn localizations(
        &self,
        map: Option<u64>,
        page: PageRequest,
    ) -> StoreResult<Page<LocalizationRecord>> {
        let client = self.client().await?;
        let rows = match map {
            Some(map) => {
                let key = self.require_map(&client, map).await?;
                let stmt = client
                    .prepare_cached(
                        "SELECT id, map_id, created_ms, document FROM localizations
                         WHERE map_id = $1 AND id < $2 ORDER BY id DESC LIMIT $3",
                    )
                    .await
                    .or_store()?;
                client
                    .query(&stmt, &[&key, &before(&page), &fetch(&page)])
                    .await
                    .or_store()?
            }
            None => {
                let stmt = client
                    .prepare_cached(
                        "SELECT id, map_id, created_ms, document FROM localizations
                         WHERE id < $1 ORDER BY id DESC LIMIT $2",
                    )
                    .await
                    .or_store()?;
                client
                    .query(&stmt, &[&before(&page), &fetch(&page)])
                    .await
                    .or_store()?
            }
        };
        let items = rows
            .iter()
            .map(localization_from_row)
            .collect::<StoreResult<Vec<_>>>()?;
        Ok(paged(items, page.limit, |r| r.id))
    }

    pub(super) async fn insert_trip(&self, new: NewTrip) -> StoreResult<TripRecord> {
        let map = db_id(new.map_id).ok_or(StoreError::MapNotFound(new.map_id))?;
        let id = db_id(new.id).ok_or(StoreError::IdTaken(new.id))?;
        let created_ms = now_ms();
        let params = document::trip_params_json(&new.params)?;
        let mut client = self.client().await?;
        // One transaction: the trip and, for a keyed request, its idempotency record.
        let tx = client.transaction().await.or_store()?;
        let stmt = tx
            .prepare_cached(
                "INSERT INTO trips (id, map_id, created_ms, closed_ms, frame_count,
                                    reference_count, status, params, base, snapshot, owner)
                 VALUES ($6, $1, $2, NULL, 0, $3, 0, $4, $5, $7, $8) RETURNING id",
            )
            .await
            .or_store()?;
        let row = tx
            .query_one(
                &stmt,
                &[
                    &map,
                    &ms(created_ms),
                    &i64::from(new.reference_count),
                    &params,
                    &new.base,
                    &id,
                    &new.snapshot,
                    &new.owner,
                ],
            )
            .await
            .map_err(|e| {
                if is_missing_parent(&e) {
                    StoreError::MapNotFound(new.map_id)
                } else if is_duplicate(&e) {
                    StoreError::IdTaken(new.id)
                } else {
                    super::db_error(e)
                }
            })?;
        let id: i64 = row.get(0);
        PgStore::claim_key(&tx, map, new.idempotency.as_ref(), None).await?;
        tx.commit().await.or_store()?;
        Ok(TripRecord {
            id: unsigned("trips", id, id)?,
            map_id: new.map_id,
            created_ms,
            closed_ms: None,
            frame_count: 0,
            reference_count: new.reference_count,
            status: None,
            params: new.params,
            owner: new.owner,
        })
    }

    pub(super) async fn trip(&self, id: u64) -> StoreResult<TripRecord> {
        let key = db_id(id).ok_or(StoreError::TripNotFound(id))?;
        let client = self.client().await?;
        let stmt = client
            .prepare_cached(&format!("SELECT {TRIP_COLUMNS} FROM trips WHERE id = $1"))
            .await
            .or_store()?;
        match client.query_opt(&stmt, &[&key]).await.or_store()? {
            Some(row) => trip_from_row(&row),
            None => Err(StoreError::TripNotFound(id)),
        }
    }

    /// The record and the state parts in one statement (so one snapshot of the database: the
    /// log rows are exactly those after the stored snapshot).
    pub(super) async fn trip_with_state(&self, id: u64) -> StoreResult<(TripRecord, TripState)> {
        let key = db_id(id).ok_or(StoreError::TripNotFound(id))?;
        let client = self.client().await?;
        let stmt = client
            .prepare_cached(&format!(
                "SELECT {TRIP_COLUMNS}, state, base, snapshot,
                        ARRAY(SELECT frame FROM trip_log WHERE trip_id = $1 ORDER BY frame),
                        ARRAY(SELECT row FROM trip_log WHERE trip_id = $1 ORDER BY frame)
                 FROM trips WHERE id = $1"
            ))
            .await
            .or_store()?;
        let Some(row) = client.query_opt(&stmt, &[&key]).await.or_store()? else {
            return Err(StoreError::TripNotFound(id));
        };
        let record = trip_from_row(&row)?;
        let legacy: Option<Vec<u8>> = row.get(9);
        let base: Option<Vec<u8>> = row.get(10);
        let snapshot: Option<Vec<u8>> = row.get(11);
        let frames: Vec<i64> = row.get(12);
        let rows: Vec<Vec<u8>> = row.get(13);
        let state = match (base, snapshot, legacy) {
            (Some(base), Some(snapshot), None) => TripState::Parts {
                base,
                snapshot,
                log: frames
                    .into_iter()
                    .map(|f| unsigned("trip_log", key, f))
                    .zip(rows)
                    .map(|(f, r)| Ok((f?, r)))
                    .collect::<StoreResult<Vec<_>>>()?,
            },
            (None, None, Some(blob)) => TripState::Legacy(blob),
            _ => {
                return Err(corrupt(
                    "trips",
                    key,
                    "neither a state blob nor state parts",
                ))
            }
        };
        Ok((record, state))
    }

    pub(super) async fn apply_trip_batch(
        &self,
        id: u64,
        batch: TripBatch,
    ) -> StoreResult<TripRecord> {
        let key = db_id(id).ok_or(StoreError::TripNotFound(id))?;
        let expected = i64::try_from(batch.expected_frames).unwrap_or(i64::MAX);
        let count = i64::try_from(batch.frame_count).unwrap_or(i64::MAX);
        // A frame may appear twice (the lag window and the batch's own estimates); the later
        // one wins, as in a sequence of writes (one upsert cannot touch a row twice).
        let latest: std::collections::BTreeMap<usize, &FrameEstimate> =
            batch.estimates.iter().map(|e| (e.frame, e)).collect();
        let frames: Vec<i64> = latest.keys().map(|&f| index(f)).collect();
        let references: Vec<Option<i64>> =
            latest.values().map(|e| e.reference.map(index)).collect();
        let confidences: Vec<f64> = latest.values().map(|e| e.confidence).collect();
        let p_correct: Vec<f64> = latest.values().map(|e| e.p_correct).collect();
        let statuses: Vec<i16> = latest
            .values()
            .map(|e| i16::from(e.status.code()))
            .collect();
        let mut client = self.client().await?;
        let tx = client.transaction().await.or_store()?;
        // Base and snapshot only when the batch changes them: an unchanged column keeps its
        // stored (TOAST) value, so the WAL carries only the small row update.
        let update = tx
            .prepare_cached(&format!(
                "UPDATE trips SET frame_count = $3, status = $4,
                        base = COALESCE($5, base), snapshot = COALESCE($6, snapshot),
                        state = CASE WHEN $5::BYTEA IS NULL THEN state END
                 WHERE id = $1 AND closed_ms IS NULL AND frame_count = $2
                 RETURNING {TRIP_COLUMNS}"
            ))
            .await
            .or_store()?;
        let updated = tx
            .query_opt(
                &update,
                &[
                    &key,
                    &expected,
                    &count,
                    &status_code(Some(batch.status)),
                    &batch.state.base,
                    &batch.state.snapshot,
                ],
            )
            .await
            .or_store()?;
        let Some(row) = updated else {
            let why = tx
                .query_opt(
                    "SELECT closed_ms IS NOT NULL, frame_count FROM trips WHERE id = $1",
                    &[&key],
                )
                .await
                .or_store()?;
            return Err(match why {
                None => StoreError::TripNotFound(id),
                Some(r) if r.get::<_, bool>(0) => StoreError::TripClosed(id),
                Some(r) => StoreError::TripConflict {
                    id,
                    stored: unsigned("trips", key, r.get(1))?,
                    expected: batch.expected_frames,
                },
            });
        };
        let record = trip_from_row(&row)?;
        let map: i64 = row.get(1);
        PgStore::claim_key(&tx, map, batch.idempotency.as_ref(), None).await?;
        if let Some(before) = batch.state.drop_log_before {
            let before = i64::try_from(before).unwrap_or(i64::MAX);
            let drop = tx
                .prepare_cached("DELETE FROM trip_log WHERE trip_id = $1 AND frame < $2")
                .await
                .or_store()?;
            tx.execute(&drop, &[&key, &before]).await.or_store()?;
        }
        if !batch.state.log.is_empty() {
            let log_frames: Vec<i64> = batch
                .state
                .log
                .iter()
                .map(|(f, _)| i64::try_from(*f).unwrap_or(i64::MAX))
                .collect();
            let log_rows: Vec<&[u8]> = batch.state.log.iter().map(|(_, r)| &r[..]).collect();
            let insert = tx
                .prepare_cached(
                    "INSERT INTO trip_log (trip_id, frame, row)
                     SELECT $1, f, r FROM unnest($2::BIGINT[], $3::BYTEA[]) AS u (f, r)",
                )
                .await
                .or_store()?;
            tx.execute(&insert, &[&key, &log_frames, &log_rows])
                .await
                .or_store()?;
        }
        if !frames.is_empty() {
            let upsert = tx
                .prepare_cached(
                    "INSERT INTO trip_frames (trip_id, frame, reference, confidence, p_correct, status)
                     SELECT $1, f, r, c, p, s
                     FROM unnest($2::BIGINT[], $3::BIGINT[], $4::DOUBLE PRECISION[],
                                 $5::DOUBLE PRECISION[], $6::SMALLINT[]) AS u (f, r, c, p, s)
                     ON CONFLICT (trip_id, frame)
                     DO UPDATE SET reference = EXCLUDED.reference, confidence = EXCLUDED.confidence,
                                   p_correct = EXCLUDED.p_correct, status = EXCLUDED.status",
                )
                .await.or_store()?;
            tx.execute(
                &upsert,
                &[
                    &key,
                    &frames,
                    &references,
                    &confidences,
                    &p_correct,
                    &statuses,
                ],
            )
            .await
            .or_store()?;
        }
        tx.commit().await.or_store()?;
        Ok(record)
    }

    pub(super) async fn close(&self, id: u64) -> StoreResult<TripRecord> {
        let key = db_id(id).ok_or(StoreError::TripNotFound(id))?;
        let client = self.client().await?;
        let stmt = client
            .prepare_cached(&format!(
                "UPDATE trips SET closed_ms = COALESCE(closed_ms, $2) WHERE id = $1
                 RETURNING {TRIP_COLUMNS}"
            ))
            .await
            .or_store()?;
        match client
            .query_opt(&stmt, &[&key, &ms(now_ms())])
            .await
            .or_store()?
        {
            Some(row) => trip_from_row(&row),
            None => Err(StoreError::TripNotFound(id)),
        }
    }

    pub(super) async fn picture(&self, id: u64) -> StoreResult<Option<Vec<u8>>> {
        let key = db_id(id).ok_or(StoreError::LocalizationNotFound(id))?;
        let client = self.client().await?;
        let stmt = client
            .prepare_cached("SELECT picture FROM localizations WHERE id = $1")
            .await
            .or_store()?;
        match client.query_opt(&stmt, &[&key]).await.or_store()? {
            Some(row) => Ok(row.get(0)),
            None => Err(StoreError::LocalizationNotFound(id)),
        }
    }

    pub(super) async fn estimates(&self, id: u64, from: u32) -> StoreResult<Vec<FrameEstimate>> {
        let key = db_id(id).ok_or(StoreError::TripNotFound(id))?;
        let client = self.client().await?;
        let stmt = client
            .prepare_cached(
                "SELECT t.id, f.frame, f.reference, f.confidence, f.p_correct, f.status
                 FROM trips t LEFT JOIN trip_frames f ON f.trip_id = t.id AND f.frame >= $2
                 WHERE t.id = $1 ORDER BY f.frame",
            )
            .await
            .or_store()?;
        let rows = client
            .query(&stmt, &[&key, &i64::from(from)])
            .await
            .or_store()?;
        if rows.is_empty() {
            return Err(StoreError::TripNotFound(id));
        }
        rows.iter()
            .filter_map(|row| {
                let frame: Option<i64> = row.get(1);
                frame.map(|f| {
                    let reference: Option<i64> = row.get(2);
                    let reference = reference
                        .map(|r| small("trip_frames", key, r).map(|r| r as usize))
                        .transpose()?;
                    let p_correct: Option<f64> = row.get(4);
                    let status: Option<i16> = row.get(5);
                    // Rows of schema 1-4 have neither.
                    let (p_correct, status) = match (p_correct, status) {
                        (Some(p), Some(s)) => (
                            p,
                            u8::try_from(s)
                                .ok()
                                .and_then(FrameStatus::from_code)
                                .ok_or_else(|| {
                                    corrupt("trip_frames", key, format!("unknown status {s}"))
                                })?,
                        ),
                        _ => (0.0, FrameStatus::before_calibration(reference)),
                    };
                    Ok(FrameEstimate {
                        frame: small("trip_frames", key, f)? as usize,
                        reference,
                        confidence: row.get(3),
                        p_correct,
                        status,
                    })
                })
            })
            .collect()
    }

    pub(super) async fn trips(&self, map: u64, page: PageRequest) -> StoreResult<Page<TripRecord>> {
        let client = self.client().await?;
        let key = self.require_map(&client, map).await?;
        let stmt = client
            .prepare_cached(&format!(
                "SELECT {TRIP_COLUMNS} FROM trips WHERE map_id = $1 AND id < $2
                 ORDER BY id DESC LIMIT $3"
            ))
            .await
            .or_store()?;
        let items = client
            .query(&stmt, &[&key, &before(&page), &fetch(&page)])
            .await
            .or_store()?
            .iter()
            .map(trip_from_row)
            .collect::<StoreResult<Vec<_>>>()?;
        Ok(paged(items, page.limit, |t| t.id))
    }
}

/// A frame or reference index as stored (`BIGINT`; every index a trip can reach fits).
fn index(i: usize) -> i64 {
    i64::try_from(i).unwrap_or(i64::MAX)
}
