//! Off the map by the stretch, online: the offline stretch rule (`confidence/stretch.rs`) on
//! the matched frames of a trip's lag window.
//!
//! Offline, a matched row is off the map when it lies in a stretch of `L` consecutive matched
//! rows whose matches stand out of their rows (robust `z`) no more, on average, than the best
//! of the `K + 1` places a route chooses from by chance, unless its own match is an outlier.
//! A detour as long as the section it bypasses is what this catches: the route drives the
//! bypassed section meanwhile, and each frame's own min-marginals cannot tell.
//!
//! A trip applies the same marks ([`crate::confidence::chance_marks`], same `L`, same bar) to
//! the matched frames of its re-traced lag window, whose matches move from batch to batch:
//! the newest frame is judged on the stretches that end at it (the causal form), a frame still
//! in the window also on those after it. Each window row's median and MAD are computed once,
//! when the row first appears in a trace ([`RowSpread`]), so a batch costs `O(lag)` beyond
//! the new rows' selections. Nothing here is persisted: the spreads are a cache of the window
//! rows, which a restored trip has bit for bit, so it marks the same frames.

use std::collections::VecDeque;

use crate::confidence::{chance_contrast, chance_marks, ConfidenceParams, RowSpread};

use super::online::RowEstimate;
use super::TripParams;

/// The stretch rule of one trip and the spreads of its window rows.
#[derive(Clone, Debug)]
pub(super) struct WindowStretch {
    /// Matched frames in a judged stretch, `L`.
    len: usize,
    /// The chance bar of the trip's fan-out, computed when a stretch is first judged.
    bar: Option<f64>,
    fan_out: usize,
    /// Frame index of `spreads[0]`.
    first: usize,
    spreads: VecDeque<Option<RowSpread>>,
}

impl WindowStretch {
    pub(super) fn new(params: &TripParams) -> Self {
        let confidence = ConfidenceParams {
            discount: Some(params.discount()),
            ..params.confidence
        };
        WindowStretch {
            len: confidence.stretch_len(),
            bar: None,
            fan_out: params.fan_out,
            first: 0,
            spreads: VecDeque::new(),
        }
    }

    /// For each matched entry of `trace` (in order), whether it is off the map by the stretch,
    /// and its contrast (the robust `z` of its match in its row).
    /// `rows` are the normalised rows of the lag window, the first of them frame `first`; every
    /// entry of `trace` is a frame of the window.
    pub(super) fn marks_and_contrasts(
        &mut self,
        first: usize,
        rows: &VecDeque<Vec<f32>>,
        trace: &[RowEstimate],
    ) -> (Vec<bool>, Vec<f64>) {
        self.sync(first, rows);
        let contrast: Vec<f64> = trace
            .iter()
            .filter_map(|e| {
                let j = e.reference?;
                let k = e.row.checked_sub(self.first)?;
                let v = rows.get(k).and_then(|r| r.get(j)).copied();
                Some(match (self.spreads.get(k).copied().flatten(), v) {
                    (Some(s), Some(v)) => s.contrast(v),
                    _ => 0.0,
                })
            })
            .collect();
        if contrast.len() < self.len.max(1) {
            // Too few matched frames for a stretch (`chance_marks` would mark none either):
            // the bar is not needed yet.
            return (vec![false; contrast.len()], contrast);
        }
        let fan_out = self.fan_out;
        let bar = *self
            .bar
            .get_or_insert_with(|| chance_contrast(fan_out.saturating_add(1)));
        (chance_marks(&contrast, self.len, bar), contrast)
    }

    /// The cached spread of window frame `frame` (after [`WindowStretch::marks_and_contrasts`]).
    pub(super) fn spread(&self, frame: usize) -> Option<RowSpread> {
        let k = frame.checked_sub(self.first)?;
        self.spreads.get(k).copied().flatten()
    }

    /// The stretch length `L`.
    pub(super) fn len(&self) -> usize {
        self.len
    }

    /// Aligns the cached spreads with the window `rows` (first frame `first`): drops those of
    /// frames that left it and computes those of frames that joined it.
    fn sync(&mut self, first: usize, rows: &VecDeque<Vec<f32>>) {
        if first < self.first || first > self.first + self.spreads.len() {
            self.spreads.clear();
            self.first = first;
        }
        while self.first < first {
            self.spreads.pop_front();
            self.first += 1;
        }
        self.spreads.truncate(rows.len());
        // At most `SAMPLE` values per row: allocated per batch, not kept with the trip.
        let mut scratch = Vec::new();
        for row in rows.iter().skip(self.spreads.len()) {
            let spread = RowSpread::of(row, &mut scratch);
            self.spreads.push_back(spread);
        }
    }

    /// Approximate heap bytes held.
    pub(super) fn heap_bytes(&self) -> usize {
        self.spreads.capacity() * std::mem::size_of::<Option<RowSpread>>()
    }
}
