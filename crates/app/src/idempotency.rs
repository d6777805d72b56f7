//! Idempotent retries (decision D5): a request that creates or appends (a map, its images,
//! descriptors, drives, trips and localizations, a trip's frames) sent with an
//! `Idempotency-Key` is applied once, however often and wherever (any replica, after a crash of
//! the first) it is retried, and every retry is answered like the first time.
//!
//! The use case stores an [`IdempotencyRecord`] — the key, a fingerprint of the request and
//! what to answer — in the same atomic store write as the batch itself, so a crash leaves both
//! or neither. A request with a key first looks the key up: found with the same fingerprint,
//! the stored answer is replayed and nothing is computed; found with another fingerprint, the
//! request is refused ([`AppError::IdempotencyKeyReused`]); not found, the batch runs and its
//! write fails with [`crate::store::StoreError::IdempotencyKeyTaken`] if a concurrent retry
//! stored the key first, after which the lookup replays that one.
//!
//! Records are kept as long as their map (deleting the map deletes them).

use std::future::Future;

use serde::{Deserialize, Serialize};

use super::error::{AppError, AppResult};
use super::App;
use crate::store::IdempotencyRecord;
use crate::ErrorCode;
use seasonloc_core::calibration::FrameStatus;
use seasonloc_core::trip::{BatchUpdate, FrameEstimate, TripStatus};

/// Longest accepted key.
pub const MAX_KEY_LEN: usize = 255;

/// A request's idempotency key and the fingerprint of what it asks.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Idempotency {
    key: String,
    fingerprint: Vec<u8>,
}

impl Idempotency {
    /// A key (1 to `MAX_KEY_LEN` visible ASCII characters) with the request's fingerprint
    /// (a hash of everything that defines the request).
    pub fn new(key: &str, fingerprint: Vec<u8>) -> AppResult<Idempotency> {
        if key.is_empty() || key.len() > MAX_KEY_LEN || !key.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(AppError::param(
                "Idempotency-Key",
                format!("must be 1 to {MAX_KEY_LEN} visible ASCII characters (e.g. a UUID)"),
            ));
        }
        Ok(Idempotency {
            key: key.to_string(),
            fingerprint,
        })
    }

    /// The key.
    pub fn key(&self) -> &str {
        &self.key
    }

    /// The record to store with the batch.
    pub(super) fn record(&self, scope: String, response: Vec<u8>) -> IdempotencyRecord {
        IdempotencyRecord {
            scope,
            key: self.key.clone(),
            fingerprint: self.fingerprint.clone(),
            response,
            indices: None,
        }
    }

    /// The stored record to replay, if the key was used; refuses a key used for another
    /// request.
    pub(super) fn replay(
        &self,
        stored: Option<IdempotencyRecord>,
    ) -> AppResult<Option<IdempotencyRecord>> {
        match stored {
            Some(r) if r.fingerprint != self.fingerprint => {
                Err(AppError::IdempotencyKeyReused(format!(
                    "Idempotency-Key `{}` was used for a different request to {}; use a new key \
                     for a new request",
                    self.key, r.scope
                )))
            }
            other => Ok(other),
        }
    }
}

impl App {
    /// The record stored under `key` in `scope`, if the key was used; refuses a key used for
    /// another request ([`AppError::IdempotencyKeyReused`]).
    pub(super) async fn stored_answer(
        &self,
        key: &Idempotency,
        scope: &str,
    ) -> AppResult<Option<IdempotencyRecord>> {
        let stored = self.store.idempotency_record(scope, key.key()).await?;
        key.replay(stored)
    }

    /// Runs a request at most once per key of `scope`, answering `(answer, replayed)`. Without a
    /// key `run(None)` just runs. With one whose record is stored, `replay(record)` answers and
    /// nothing runs. Otherwise `run` gets the record to store in the same write as its change
    /// (it may fill in the record's `response`); if a concurrent request with the same key
    /// stored first, the write fails (code `map_changed`) and that request's record is
    /// replayed.
    pub(super) async fn once<T, R, RFut, F, FFut>(
        &self,
        key: Option<Idempotency>,
        scope: String,
        replay: R,
        run: F,
    ) -> AppResult<(T, bool)>
    where
        R: Fn(IdempotencyRecord) -> RFut,
        RFut: Future<Output = AppResult<T>>,
        F: FnOnce(Option<IdempotencyRecord>) -> FFut,
        FFut: Future<Output = AppResult<T>>,
    {
        let Some(key) = key else {
            return Ok((run(None).await?, false));
        };
        if let Some(record) = self.stored_answer(&key, &scope).await? {
            tracing::info!(%scope, key = %record.key, "idempotent retry answered from its record");
            return Ok((replay(record).await?, true));
        }
        match run(Some(key.record(scope.clone(), Vec::new()))).await {
            Err(e) if e.code() == ErrorCode::MapChanged => {
                match self.stored_answer(&key, &scope).await? {
                    Some(record) => Ok((replay(record).await?, true)),
                    None => Err(e),
                }
            }
            other => other.map(|answer| (answer, false)),
        }
    }
}

/// A creation's stored answer: the id of what it created.
pub(super) fn id_answer(id: u64) -> Vec<u8> {
    id.to_le_bytes().to_vec()
}

/// [`id_answer`] read back.
pub(super) fn answered_id(record: &IdempotencyRecord) -> AppResult<u64> {
    let Ok::<[u8; 8], _>(id) = record.response.as_slice().try_into() else {
        return Err(AppError::Internal(format!(
            "the stored answer of key `{}` is {} bytes, not an id",
            record.key,
            record.response.len()
        )));
    };
    Ok(u64::from_le_bytes(id))
}

/// What a trip batch answered, as stored for replays.
#[derive(Serialize, Deserialize)]
struct FramesReplay {
    frame_count: u64,
    status: u8,
    hidden_cost: f64,
    /// `[frame, reference or null, confidence]`.
    estimates: Vec<(usize, Option<usize>, f64)>,
    window: Vec<(usize, Option<usize>, f64)>,
    /// `[p_correct, status code]` of each of `estimates` / `window` (absent in replays
    /// stored before the calibration: read as `p_correct` 0 and
    /// [`FrameStatus::before_calibration`]).
    #[serde(default)]
    estimates_trust: Vec<(f64, u8)>,
    #[serde(default)]
    window_trust: Vec<(f64, u8)>,
}

fn trust(e: &[FrameEstimate]) -> Vec<(f64, u8)> {
    e.iter().map(|e| (e.p_correct, e.status.code())).collect()
}

fn status_code(s: TripStatus) -> u8 {
    match s {
        TripStatus::Localized => 1,
        TripStatus::Lost => 2,
        TripStatus::Relocalized => 3,
    }
}

fn estimates(e: &[FrameEstimate]) -> Vec<(usize, Option<usize>, f64)> {
    e.iter()
        .map(|e| (e.frame, e.reference, e.confidence))
        .collect()
}

fn frames(e: Vec<(usize, Option<usize>, f64)>, trust: &[(f64, u8)]) -> Vec<FrameEstimate> {
    e.into_iter()
        .enumerate()
        .map(|(k, (frame, reference, confidence))| {
            let (p_correct, status) = trust.get(k).map_or_else(
                || (0.0, FrameStatus::before_calibration(reference)),
                |&(p, code)| (p, FrameStatus::from_code(code).unwrap_or(FrameStatus::Lost)),
            );
            FrameEstimate {
                frame,
                reference,
                confidence,
                p_correct,
                status,
            }
        })
        .collect()
}

/// The stored answer of a trip batch.
pub(super) fn encode_frames(
    frame_count: u64,
    update: &BatchUpdate,
    hidden_cost: f64,
) -> AppResult<Vec<u8>> {
    serde_json::to_vec(&FramesReplay {
        frame_count,
        status: status_code(update.status),
        hidden_cost,
        estimates: estimates(&update.estimates),
        window: estimates(&update.window),
        estimates_trust: trust(&update.estimates),
        window_trust: trust(&update.window),
    })
    .map_err(|e| AppError::Internal(format!("encoding a replay: {e}")))
}

/// A stored trip answer: frames after the batch, the update, the hidden cost.
pub(super) fn decode_frames(bytes: &[u8]) -> AppResult<(u64, BatchUpdate, f64)> {
    let r: FramesReplay = serde_json::from_slice(bytes)
        .map_err(|e| AppError::Internal(format!("a stored replay is unreadable: {e}")))?;
    let status = match r.status {
        1 => TripStatus::Localized,
        2 => TripStatus::Lost,
        3 => TripStatus::Relocalized,
        s => return Err(AppError::Internal(format!("stored replay status {s}"))),
    };
    Ok((
        r.frame_count,
        BatchUpdate {
            estimates: frames(r.estimates, &r.estimates_trust),
            window: frames(r.window, &r.window_trust),
            status,
        },
        r.hidden_cost,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_checked_and_answers_round_trip() {
        assert!(Idempotency::new("", vec![]).is_err());
        assert!(Idempotency::new("a b", vec![]).is_err());
        assert!(Idempotency::new(&"k".repeat(256), vec![]).is_err());
        let k = Idempotency::new("batch-7", vec![1, 2]).unwrap();
        let stored = k.record("trip/x".into(), vec![]);
        assert_eq!(k.replay(Some(stored.clone())).unwrap(), Some(stored));
        let other = Idempotency::new("batch-7", vec![3]).unwrap();
        let e = other
            .replay(Some(k.record("trip/x".into(), vec![])))
            .unwrap_err();
        assert!(matches!(e, AppError::IdempotencyKeyReused(_)), "{e}");
        let update = BatchUpdate {
            estimates: vec![FrameEstimate {
                frame: 4,
                reference: None,
                confidence: 0.0,
                p_correct: 0.0,
                status: FrameStatus::OffMap,
            }],
            window: vec![FrameEstimate {
                frame: 3,
                reference: Some(9),
                confidence: 0.25,
                p_correct: 0.125,
                status: FrameStatus::Uncertain,
            }],
            status: TripStatus::Relocalized,
        };
        let bytes = encode_frames(5, &update, 1.5).unwrap();
        assert_eq!(decode_frames(&bytes).unwrap(), (5, update, 1.5));
    }
}
