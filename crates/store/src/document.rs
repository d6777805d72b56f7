//! The stored documents' one encoding, shared by every engine: a localization's result as one
//! flat JSON object, a trip's parameters as JSON. The documents themselves are the domain
//! model's serde forms (`seasonloc_app::model`, with the core's hypotheses, predictions and
//! trip parameters); this module adds only the envelope.
//!
//! The JSON written here is byte for byte what layout 4 stores (field order, names, number
//! formats; `tests/data/store-layout4.golden` checks it): a localization document is a JSON
//! object with the localization's id and map id as 16 lowercase hex digits and its creation
//! time, then the result's fields, not nested. The API answers a stored result with these
//! bytes. Changing any of it is a layout change (`migrations/README.md`).

use serde::de::Error as _;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use seasonloc_app::model::{
    LocalizationParams, LocalizationRecord, LocalizationResult, LocalizationTimings, PictureInfo,
};
use seasonloc_app::store::{StoreError, StoreResult};
use seasonloc_core::localize::Prediction;
use seasonloc_core::solver::Hypothesis;
use seasonloc_core::trip::TripParams;

/// The stored JSON object: identity first, then the result's fields (no nesting).
#[derive(Serialize)]
struct FlatOut<'a> {
    #[serde(serialize_with = "hex_out")]
    id: u64,
    #[serde(serialize_with = "hex_out")]
    map_id: u64,
    created_at_ms: u64,
    query_count: usize,
    reference_count: usize,
    params: &'a LocalizationParams,
    total_cost: f64,
    hypotheses: &'a [Hypothesis],
    predictions: &'a [Prediction],
    timings: &'a LocalizationTimings,
    #[serde(skip_serializing_if = "Option::is_none")]
    picture: Option<&'a PictureInfo>,
}

#[derive(Deserialize)]
struct FlatIn {
    #[serde(deserialize_with = "hex_in")]
    id: u64,
    #[serde(deserialize_with = "hex_in")]
    map_id: u64,
    created_at_ms: u64,
    query_count: usize,
    reference_count: usize,
    params: LocalizationParams,
    total_cost: f64,
    hypotheses: Vec<Hypothesis>,
    predictions: Vec<Prediction>,
    timings: LocalizationTimings,
    #[serde(default)]
    picture: Option<PictureInfo>,
}

fn hex_out<S: Serializer>(id: &u64, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(&format!("{id:016x}"))
}

fn hex_in<'de, D: Deserializer<'de>>(d: D) -> Result<u64, D::Error> {
    let s = String::deserialize(d)?;
    if s.len() == 16 && s.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f')) {
        u64::from_str_radix(&s, 16).map_err(D::Error::custom)
    } else {
        Err(D::Error::custom(format!("`{s}` is not a 16-digit hex id")))
    }
}

/// The stored JSON bytes of a localization.
pub fn localization_json(l: &LocalizationRecord) -> StoreResult<Vec<u8>> {
    let r = &l.result;
    let flat = FlatOut {
        id: l.id,
        map_id: l.map_id,
        created_at_ms: l.created_ms,
        query_count: r.query_count,
        reference_count: r.reference_count,
        params: &r.params,
        total_cost: r.total_cost,
        hypotheses: &r.hypotheses,
        predictions: &r.predictions,
        timings: &r.timings,
        picture: r.picture.as_ref(),
    };
    serde_json::to_vec(&flat).map_err(|e| StoreError::Backend(Box::new(e)))
}

/// Decodes the JSON of a localization stored under `key`.
pub fn localization_from_json(key: &[u8], bytes: &[u8]) -> StoreResult<LocalizationRecord> {
    let f: FlatIn = serde_json::from_slice(bytes)
        .map_err(|e| StoreError::corrupt(key, format!("localization document: {e}")))?;
    Ok(LocalizationRecord {
        id: f.id,
        map_id: f.map_id,
        created_ms: f.created_at_ms,
        result: LocalizationResult {
            query_count: f.query_count,
            reference_count: f.reference_count,
            params: f.params,
            total_cost: f.total_cost,
            hypotheses: f.hypotheses,
            predictions: f.predictions,
            timings: f.timings,
            picture: f.picture,
        },
    })
}

/// [`localization_from_json`], checked against the identity the engine keeps beside the
/// document (its key or columns): a document that names another localization or map is
/// corrupt.
pub fn localization_checked(
    key: &[u8],
    bytes: &[u8],
    id: u64,
    map_id: u64,
) -> StoreResult<LocalizationRecord> {
    let l = localization_from_json(key, bytes)?;
    if (l.id, l.map_id) != (id, map_id) {
        return Err(StoreError::corrupt(
            key,
            format!(
                "the document names localization {:016x} of map {:016x}, stored as {id:016x} of {map_id:016x}",
                l.id, l.map_id
            ),
        ));
    }
    Ok(l)
}

/// The stored JSON bytes of a trip's parameters.
pub fn trip_params_json(p: &TripParams) -> StoreResult<Vec<u8>> {
    serde_json::to_vec(p).map_err(|e| StoreError::Backend(Box::new(e)))
}

/// Decodes the parameters of a trip stored under `key`.
pub fn trip_params_from_json(key: &[u8], bytes: &[u8]) -> StoreResult<TripParams> {
    serde_json::from_slice(bytes)
        .map_err(|e| StoreError::corrupt(key, format!("trip parameters: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use seasonloc_core::localize::LocalizeOptions;

    #[test]
    fn localization_json_is_flat_with_hex_ids_and_round_trips() {
        let doc = LocalizationRecord {
            id: 0xab,
            map_id: 1,
            created_ms: 5,
            result: LocalizationResult {
                query_count: 1,
                reference_count: 2,
                params: LocalizationParams::new(&LocalizeOptions::default(), 1.25, None),
                total_cost: 3.5,
                hypotheses: Vec::new(),
                predictions: vec![Prediction {
                    query: 0,
                    reference: 1,
                    confidence: 0.5,
                    p_correct: None,
                }],
                timings: LocalizationTimings::default(),
                picture: None,
            },
        };
        let json = localization_json(&doc).unwrap();
        let text = String::from_utf8(json.clone()).unwrap();
        assert!(
            text.starts_with(
                r#"{"id":"00000000000000ab","map_id":"0000000000000001","created_at_ms":5,"query_count":1,"#
            ),
            "{text}"
        );
        assert!(text.contains(r#""hidden_cost_mode":"auto""#), "{text}");
        assert!(
            text.contains(r#""predictions":[{"query":0,"ref":1,"confidence":0.5}]"#),
            "{text}"
        );
        assert!(!text.contains("method"), "{text}");
        assert_eq!(localization_from_json(b"L", &json).unwrap(), doc);
        assert_eq!(localization_checked(b"L", &json, 0xab, 1).unwrap(), doc);
        assert!(localization_checked(b"L", &json, 0xac, 1).is_err());
        let err = localization_from_json(b"L", b"{}").unwrap_err();
        assert!(matches!(err, StoreError::Corrupt { .. }), "{err}");
        let bad_id = text.replace("00000000000000ab", "xyz");
        assert!(localization_from_json(b"L", bad_id.as_bytes()).is_err());
    }

    #[test]
    fn trip_parameters_are_stored_as_before_and_read_with_the_trip_confidence() {
        let p = TripParams::default();
        let json = String::from_utf8(trip_params_json(&p).unwrap()).unwrap();
        assert_eq!(
            json,
            r#"{"fan_out":4,"hidden_cost":null,"horizontal":true,"lag":32,"relocalization_cost":1.0,"prior_weight":100.0,"normalize":true}"#
        );
        assert_eq!(trip_params_from_json(b"T", json.as_bytes()).unwrap(), p);
    }
}
