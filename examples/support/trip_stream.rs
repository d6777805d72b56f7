//! Streaming a similarity matrix through an online trip, shared by the examples that score
//! trips (`trip_nordland`, `cooc_gardens`): the estimates at arrival and after the lag window,
//! and their predictions for `seasonloc_core::eval`. The trip tests (`tests/trip_jump/`,
//! `tests/derived_routes/`) stream through it too.

#![allow(dead_code)] // each includer uses a different part

use seasonloc_core::eval::Prediction;
use seasonloc_core::trip::{FrameEstimate, Trip, TripParams};
use seasonloc_core::Matrix;

/// Streams `c` (the trip's rows) through a trip in batches of `batch`; returns the estimates
/// as reported at arrival and as finally kept (after the lag window).
pub fn stream(
    c: &Matrix,
    prior: &[f32],
    params: TripParams,
    batch: usize,
) -> (Vec<FrameEstimate>, Vec<FrameEstimate>) {
    let mut trip = Trip::new(prior.to_vec(), params).expect("valid parameters");
    let mut arrival = Vec::new();
    let mut last = Vec::new();
    for start in (0..c.rows()).step_by(batch) {
        let end = (start + batch).min(c.rows());
        let rows: Vec<&[f32]> = (start..end).map(|i| c.row(i)).collect();
        let u = trip
            .push_batch(&Matrix::from_rows(&rows).expect("rows"))
            .expect("batch");
        arrival.extend(&u.estimates);
        last.extend(&u.estimates);
        for w in &u.window {
            last[w.frame] = *w;
        }
    }
    (arrival, last)
}

/// The predictions of the estimates that name a reference (hidden frames give none).
pub fn predictions(e: &[FrameEstimate]) -> Vec<Prediction> {
    e.iter()
        .filter_map(|e| {
            e.reference.map(|j| Prediction {
                query: e.frame,
                reference: j,
                confidence: e.confidence,
                p_correct: None,
            })
        })
        .collect()
}
