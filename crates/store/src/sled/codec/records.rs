//! The records besides maps and images: localizations (ids, time, the stored document's
//! JSON), trips (record and status code), per-frame estimates, and the idempotency records
//! of requests sent with an `Idempotency-Key`.

use super::value::{Reader, Writer};
use seasonloc_app::model::{LocalizationRecord, TripRecord};
use seasonloc_app::store::{IdempotencyRecord, StoreError};
use seasonloc_core::calibration::FrameStatus;
use seasonloc_core::trip::FrameEstimate;
use seasonloc_core::trip::TripStatus;

/// Encodes an idempotency record (its scope and key are in the record's key).
pub fn encode_idempotency(r: &IdempotencyRecord) -> Vec<u8> {
    let mut w = Writer::new();
    w.bytes(&r.fingerprint);
    w.bytes(&r.response);
    match &r.indices {
        None => w.u8(0),
        Some(range) => {
            w.u8(1);
            w.u32(range.start);
            w.u32(range.end);
        }
    }
    w.into_bytes()
}

/// Decodes the idempotency record of `scope` and `key` stored under `k`.
pub fn decode_idempotency(
    k: &[u8],
    scope: &str,
    key: &str,
    value: &[u8],
) -> Result<IdempotencyRecord, StoreError> {
    let mut r = Reader::new(k, value)?;
    let fingerprint = r.bytes()?.to_vec();
    let response = r.bytes()?.to_vec();
    let indices = match r.u8()? {
        0 => None,
        1 => Some(r.u32()?..r.u32()?),
        t => return Err(StoreError::corrupt(k, format!("bad option tag {t}"))),
    };
    r.finish()?;
    Ok(IdempotencyRecord {
        scope: scope.to_string(),
        key: key.to_string(),
        fingerprint,
        response,
        indices,
    })
}

/// Encodes a localization record: ids and time, then the document's JSON
/// ([`crate::document::localization_json`]).
pub fn encode_localization(l: &LocalizationRecord) -> Result<Vec<u8>, StoreError> {
    let mut w = Writer::new();
    w.u64(l.id);
    w.u64(l.map_id);
    w.u64(l.created_ms);
    w.bytes(&crate::document::localization_json(l)?);
    Ok(w.into_bytes())
}

/// The stored code of a trip status (0: no batch yet).
fn status_code(s: Option<TripStatus>) -> u8 {
    match s {
        None => 0,
        Some(TripStatus::Localized) => 1,
        Some(TripStatus::Lost) => 2,
        Some(TripStatus::Relocalized) => 3,
    }
}

fn status_of(key: &[u8], code: u8) -> Result<Option<TripStatus>, StoreError> {
    match code {
        0 => Ok(None),
        1 => Ok(Some(TripStatus::Localized)),
        2 => Ok(Some(TripStatus::Lost)),
        3 => Ok(Some(TripStatus::Relocalized)),
        c => Err(StoreError::corrupt(key, format!("unknown trip status {c}"))),
    }
}

/// Encodes a trip record (its parameters as [`crate::document::trip_params_json`]).
pub fn encode_trip(t: &TripRecord) -> Result<Vec<u8>, StoreError> {
    let mut w = Writer::new();
    w.u64(t.id);
    w.u64(t.map_id);
    w.u64(t.created_ms);
    match t.closed_ms {
        None => w.u8(0),
        Some(ms) => {
            w.u8(1);
            w.u64(ms);
        }
    }
    w.u64(t.frame_count);
    w.u32(t.reference_count);
    w.u8(status_code(t.status));
    w.bytes(&crate::document::trip_params_json(&t.params)?);
    // The owner is a trailer: records written before it end after the parameters.
    if let Some(owner) = &t.owner {
        w.str(owner);
    }
    Ok(w.into_bytes())
}

/// Decodes a trip record.
pub fn decode_trip(key: &[u8], value: &[u8]) -> Result<TripRecord, StoreError> {
    let mut r = Reader::new(key, value)?;
    let id = r.u64()?;
    let map_id = r.u64()?;
    let created_ms = r.u64()?;
    let closed_ms = match r.u8()? {
        0 => None,
        1 => Some(r.u64()?),
        t => return Err(StoreError::corrupt(key, format!("bad option tag {t}"))),
    };
    let frame_count = r.u64()?;
    let reference_count = r.u32()?;
    let status = status_of(key, r.u8()?)?;
    let params = crate::document::trip_params_from_json(key, r.bytes()?)?;
    let owner = if r.remaining() == 0 {
        None
    } else {
        Some(r.str()?)
    };
    r.finish()?;
    Ok(TripRecord {
        id,
        map_id,
        created_ms,
        closed_ms,
        frame_count,
        reference_count,
        status,
        params,
        owner,
    })
}

/// A frame or reference index as the layout stores it (`u32`; a map holds at most
/// `u32::MAX` images and a trip's frames are counted in a `u32` by the layout too).
pub fn small_index(i: usize) -> Result<u32, StoreError> {
    u32::try_from(i).map_err(|_| StoreError::Backend(format!("index {i} is over 2^32").into()))
}

/// Encodes a frame's estimate (layout 7): the reference, the confidence, `p_correct` and the
/// status's code.
pub fn encode_frame(f: &FrameEstimate) -> Result<Vec<u8>, StoreError> {
    let mut w = Writer::new();
    match f.reference {
        None => w.u8(0),
        Some(j) => {
            w.u8(1);
            w.u32(small_index(j)?);
        }
    }
    w.f64(f.confidence);
    w.f64(f.p_correct);
    w.u8(f.status.code());
    Ok(w.into_bytes())
}

/// Decodes a frame's estimate stored under `key` (the frame index comes from the key).
pub fn decode_frame(key: &[u8], value: &[u8]) -> Result<FrameEstimate, StoreError> {
    let frame = key
        .get(9..13)
        .and_then(|b| b.try_into().ok())
        .map(u32::from_be_bytes)
        .ok_or_else(|| StoreError::corrupt(key, "key too short for a frame"))?;
    let mut r = Reader::new(key, value)?;
    let reference = match r.u8()? {
        0 => None,
        1 => Some(r.u32()?),
        t => return Err(StoreError::corrupt(key, format!("bad option tag {t}"))),
    };
    let confidence = r.f64()?;
    let reference = reference.map(|j| j as usize);
    // Layouts up to 6 stored neither `p_correct` nor a status.
    let (p_correct, status) = if r.remaining() == 0 {
        (0.0, FrameStatus::before_calibration(reference))
    } else {
        let p = r.f64()?;
        let code = r.u8()?;
        let status = FrameStatus::from_code(code)
            .ok_or_else(|| StoreError::corrupt(key, format!("unknown frame status {code}")))?;
        (p, status)
    };
    r.finish()?;
    Ok(FrameEstimate {
        frame: frame as usize,
        reference,
        confidence,
        p_correct,
        status,
    })
}

/// The id and map id of a localization record, without decoding its document.
pub fn decode_localization_ids(key: &[u8], value: &[u8]) -> Result<(u64, u64), StoreError> {
    let mut r = Reader::new(key, value)?;
    Ok((r.u64()?, r.u64()?))
}

/// Decodes a localization record: its document, checked against the ids beside it (the
/// creation time clients see is the document's).
pub fn decode_localization(key: &[u8], value: &[u8]) -> Result<LocalizationRecord, StoreError> {
    let mut r = Reader::new(key, value)?;
    let id = r.u64()?;
    let map_id = r.u64()?;
    let _created_ms = r.u64()?;
    let record = crate::document::localization_checked(key, r.bytes()?, id, map_id)?;
    r.finish()?;
    Ok(record)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
            #[test]
            fn localization_round_trip(
                queries in 0usize..10_000,
                cost in -1e6f64..1e6,
                confidences in proptest::collection::vec(0.0f64..1e3, 0..20),
                id in any::<u64>(),
            ) {
                use seasonloc_app::model::{LocalizationParams, LocalizationResult, LocalizationTimings};
    use seasonloc_core::localize::Prediction;
                let result = LocalizationResult {
                    query_count: queries,
                    reference_count: 3,
                    params: LocalizationParams::new(&seasonloc_core::localize::LocalizeOptions::default(), cost.abs(), None),
                    total_cost: cost,
                    hypotheses: Vec::new(),
                    predictions: confidences
                        .iter()
                        .enumerate()
                        .map(|(k, &c)| Prediction { query: k, reference: k + 1, confidence: c, p_correct: None })
                        .collect(),
                    timings: LocalizationTimings::default(),
                    picture: None,
                };
                let l = LocalizationRecord { id, map_id: 3, created_ms: 5, result };
                prop_assert_eq!(decode_localization(b"L", &encode_localization(&l).unwrap()).unwrap(), l);
            }
        }

    /// A trip's owner is a trailer: a record with one reads it back, a record without one
    /// (every layout before 8) reads as none, and bytes after the owner are refused.
    #[test]
    fn a_trip_record_keeps_its_owner_and_older_records_have_none() {
        use seasonloc_core::trip::TripParams;
        let mut t = TripRecord {
            id: 9,
            map_id: 3,
            created_ms: 5,
            closed_ms: Some(6),
            frame_count: 40,
            reference_count: 12,
            status: Some(TripStatus::Localized),
            params: TripParams::default(),
            owner: None,
        };
        let plain = encode_trip(&t).unwrap();
        assert_eq!(decode_trip(b"T", &plain).unwrap(), t);
        t.owner = Some("vehicle-7".into());
        let owned = encode_trip(&t).unwrap();
        assert!(
            owned.starts_with(&plain),
            "the owner is appended after the parameters"
        );
        assert_eq!(decode_trip(b"T", &owned).unwrap(), t);
        let mut longer = owned.clone();
        longer.push(0);
        assert!(decode_trip(b"T", &longer).is_err());
    }
}
