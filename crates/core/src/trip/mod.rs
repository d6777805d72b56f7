//! A trip: online localization of a vehicle that posts frames as it drives.
//!
//! A [`Trip`] turns each batch of raw cosine rows (new frames against the map) into per-frame
//! estimates, using bounded state only:
//!
//! * **Online column normalisation.** Eq. 2 divides each column by its mean over *all* queries,
//!   which are unknown while driving. A trip divides by a running estimate instead:
//!   `m_j = (n0 · s · p_j + Σ_i c_ij) / (n0 + n)`, where `p_j` is the map's *prior* column mean
//!   (the mean similarity of reference `j` to a sample of the map's own images, computed once
//!   per map by [`column_prior`]), `s` rescales that prior to the trip's similarity level (the
//!   ratio of the trip's mean similarity to the prior's), `n` counts the frames seen and
//!   `n0` = [`TripParams::prior_weight`] (default 100 frames). Early frames are normalised
//!   mostly by the prior, later ones mostly by what the trip has seen. Each row is normalised once,
//!   when it arrives, and never revised (revising would mean re-solving from the start).
//!   The means are floored at half their median, as the offline default, so a near-empty
//!   reference cannot get an exploding `ĉ` (README, Trips, for the measured effect).
//! * **Hidden cost.** `auto` resolves `W` once, from the first batch's normalised rows, with the
//!   same quantile rule as offline ([`crate::solver::auto_hidden_cost`]), and keeps it for the
//!   trip so the path costs stay comparable.
//! * **The path** is [`online::OnlineSolver`] (O(D) per frame, back-pointers for a lag
//!   window, optional relocalization). A batch longer than the lag window is fed in chunks of
//!   at most `lag` frames, so every frame is traced while it is in the window.
//! * **Confidence** of a frame is the offline default, the discounted min-marginal ratio, on
//!   the frames so far (`trip/confidence.rs`): causal at arrival (the forward pass alone, the scored
//!   frame last), re-scored with the later frames while it stays in the lag window. Its cost
//!   per batch is `2 · lag` row steps, whatever the trip's length.
//! * **Off the map by the stretch** (`trip/stretch.rs`): the offline stretch rule on the
//!   matched frames of the re-traced lag window. A frame in a stretch of `L` matched frames
//!   whose matches stand out of their rows no more than chance is reported without a reference
//!   (confidence 0); the newest frame is judged on the stretches that end at it.
//! * **Status** of the latest frame: `lost` when it has no reference (hidden, or off the map by
//!   the stretch) or its confidence is at most [`LOST_RATIO`] (no local evidence for the
//!   match), `relocalized` when the best path entered one of this batch's frames by a
//!   relocalization jump, else `localized`.
//! * **Stored form** ([`persist`]): a constant *base* (parameters and prior, written once), a
//!   *snapshot* of the trip at the start of its lag window, and a *log* of the raw rows since
//!   the snapshot. A batch writes its raw rows (`4 · D` bytes per frame) and, once every `lag`
//!   frames, a new snapshot (`O(D)`): [`Trip::take_delta`]. [`Trip::restore`] replays the log
//!   on the snapshot with the same row steps, so a restored trip is bit-identical to the live
//!   one.
//!
//! This file is the driver ([`Trip`]: batches, status); the parameters and answers are in
//! `params.rs`, when and what to persist and the restore by replay in `storage.rs`.

use std::collections::VecDeque;

use crate::calibration::{self, FrameStatus};
use crate::confidence::GraphParams;
use crate::solver::auto_hidden_cost;
use crate::{Error, Matrix, Result};

mod confidence;
mod evidence;
mod normalize;
pub mod online;
mod params;
pub mod persist;
pub mod state;
mod storage;
mod stretch;

use confidence::{Discount, DiscountedForward};
pub use evidence::FrameEvidence;
pub use normalize::column_prior;
use normalize::{NormScratch, Prior, Sums};
use online::{OnlineParams, OnlineSolver, RowEstimate};
pub use params::{
    BatchUpdate, FrameEstimate, TripParams, TripStatus, DEFAULT_RELOCALIZATION_COST,
    DEFAULT_TOLERANCE, LOST_RATIO, MAX_CONFIDENCE_WINDOW, MAX_TOLERANCE,
};
pub use persist::{StateDelta, StoredState};
use stretch::WindowStretch;

/// Largest lag window of a trip in cells (`lag` x the map's references): about 300 MiB of
/// state. The default lag of 32 stays below it up to 524,288 references.
pub const MAX_WINDOW_CELLS: usize = 1 << 24;

/// The raw rows of the lag window and the normalisation sums before it: what a trip needs to
/// write a snapshot at the start of its window. Absent for a trip continued from a format-1
/// state (which kept neither; it stores a full image per batch instead, see [`persist`]).
#[derive(Clone)]
struct LogWindow {
    raw: VecDeque<Vec<f32>>,
    base: Sums,
}

/// What the store holds of this trip: the bookkeeping behind [`Trip::take_delta`].
#[derive(Clone, Copy, Debug, PartialEq)]
struct Stored {
    /// Frames of the stored snapshot (the log holds the rows from there on).
    snapshot_row: usize,
    /// Whether the stored snapshot has the solver (so the resolved `W`).
    snapshot_has_solver: bool,
    /// Whether the store holds this format's base (false for a trip read from format 1).
    base_written: bool,
}

/// One trip's bounded state.
#[derive(Clone)]
pub struct Trip {
    params: TripParams,
    prior: Vec<f32>,
    prior_mean: f64,
    /// Running sums of the online normalisation after the latest frame.
    sums: Sums,
    frames: usize,
    solver: Option<OnlineSolver>,
    /// The discounted forward value of the row before the solver's lag window.
    disc: DiscountedForward,
    log: Option<LogWindow>,
    stored: Stored,
    pending: StateDelta,
    /// The stretch rule on the lag window (a cache of the window rows: not persisted).
    stretch: WindowStretch,
    /// The prior over its median (derived from the prior: not persisted).
    prior_rel: Vec<f32>,
    /// The evidence of every frame the last batch reported (not persisted: an answer).
    last_evidence: Vec<FrameEvidence>,
}

impl Trip {
    /// A trip on a map whose prior column means are `prior` (see [`column_prior`]).
    pub fn new(prior: Vec<f32>, params: TripParams) -> Result<Self> {
        if prior.is_empty() {
            return Err(Error::Empty("the map has no reference images".into()));
        }
        params.validate()?;
        let d = prior.len();
        // The lag window keeps about 19 bytes per cell (back-pointers, `ĉ`, raw rows) of
        // `lag x D`: bounded per trip so that one trip cannot take the server's memory.
        let cells = d.saturating_mul(params.lag);
        if cells > MAX_WINDOW_CELLS {
            return Err(Error::inconsistent(
                "lag",
                format!(
                    "a lag window of {} frames on a map of {d} references keeps {cells} cells \
                     of state; at most {MAX_WINDOW_CELLS} (a lag of at most {} on this map)",
                    params.lag,
                    MAX_WINDOW_CELLS / d
                ),
            ));
        }
        let prior_mean = prior.iter().map(|v| f64::from(*v)).sum::<f64>() / d as f64;
        let mut sorted = prior.clone();
        let mid = sorted.len() / 2;
        let median = *sorted.select_nth_unstable_by(mid, f32::total_cmp).1;
        let prior_rel = prior
            .iter()
            .map(|&p| if median > 0.0 { p / median } else { 0.0 })
            .collect();
        Ok(Trip {
            params,
            sums: Sums::new(d),
            prior,
            prior_mean,
            frames: 0,
            solver: None,
            disc: DiscountedForward::default(),
            log: Some(LogWindow {
                raw: VecDeque::new(),
                base: Sums::new(d),
            }),
            stored: Stored {
                snapshot_row: 0,
                snapshot_has_solver: false,
                base_written: true,
            },
            pending: StateDelta::default(),
            stretch: WindowStretch::new(&params),
            prior_rel,
            last_evidence: Vec::new(),
        })
    }

    /// The evidence of every frame the last batch reported (its new frames and the
    /// re-traced lag window), in frame order; see [`FrameEvidence`].
    pub fn last_evidence(&self) -> &[FrameEvidence] {
        &self.last_evidence
    }

    /// Frames consumed so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The hidden cost in use (`None` before the first batch when it is automatic).
    pub fn hidden_cost(&self) -> Option<f64> {
        self.solver
            .as_ref()
            .map(|s| s.params().graph.hidden_cost)
            .or(self.params.hidden_cost)
    }

    /// The trip's parameters.
    pub fn params(&self) -> &TripParams {
        &self.params
    }

    /// Number of map references the trip localizes against.
    pub fn references(&self) -> usize {
        self.prior.len()
    }

    /// Approximate heap bytes held by this trip (vectors' capacities), for memory reports and
    /// the service's cache of open trips.
    pub fn heap_bytes(&self) -> usize {
        let log = self.log.as_ref().map_or(0, |l| {
            l.raw.iter().map(|r| r.capacity() * 4).sum::<usize>() + l.base.columns.capacity() * 8
        });
        self.prior.capacity() * 4
            + self.sums.columns.capacity() * 8
            + self.solver.as_ref().map_or(0, |s| s.heap_bytes())
            + self.disc.heap_bytes()
            + log
            + self.pending.heap_bytes()
            + self.stretch.heap_bytes()
            + self.prior_rel.capacity() * 4
            + self.last_evidence.capacity() * std::mem::size_of::<FrameEvidence>()
    }

    /// The graph and discount the confidence scores with (the solver's `W` once resolved).
    fn discount(&self, graph: GraphParams) -> Discount {
        Discount {
            graph,
            g: self.params.discount(),
            radius: self.params.confidence.radius,
        }
    }

    /// Normalises a batch with the running column means (see the module doc), updating them.
    fn normalize_batch(&mut self, c: &Matrix) -> Matrix {
        if !self.params.normalize {
            return c.clone();
        }
        let prior = Prior {
            means: &self.prior,
            mean: self.prior_mean,
            weight: self.params.prior_weight,
        };
        let mut out = Matrix::zeros(c.rows(), c.cols());
        let mut scratch = NormScratch::default();
        for (i, row) in c.iter_rows().enumerate() {
            prior.normalize_row(
                &mut self.sums,
                self.frames + i + 1,
                row,
                out.row_mut(i),
                &mut scratch,
            );
        }
        out
    }

    /// Feeds one frame's normalised row (and its raw row) to the solver. A row leaving the
    /// lag window advances the window base: the solver's costs, the discounted forward value
    /// and the normalisation sums before the window.
    fn push_row(&mut self, raw: &[f32], chat: Vec<f32>) -> Result<()> {
        let Some(solver) = self.solver.as_mut() else {
            return Err(Error::Format {
                path: "trip state".into(),
                reason: "rows before the solver exists".into(),
            });
        };
        let graph = solver.params().graph;
        let left = solver.push_row_leaving(chat)?;
        if let Some(log) = &mut self.log {
            log.raw.push_back(raw.to_vec());
        }
        if let Some(row) = left {
            let discount = self.discount(graph);
            self.disc.advance(&discount, &row);
            if let Some(log) = &mut self.log {
                if let Some(r) = log.raw.pop_front() {
                    if self.params.normalize {
                        log.base.add(&r);
                    }
                }
            }
        }
        self.frames += 1;
        Ok(())
    }

    /// The best path over the lag window with each matched row's confidence and evidence; a
    /// row the stretch rule puts off the map (`stretch.rs`) is reported without a reference,
    /// at 0.
    fn score_window(&mut self) -> Vec<(RowEstimate, f64, FrameEvidence)> {
        let bands = self.window_bands();
        let Some(solver) = &self.solver else {
            return Vec::new();
        };
        let rows = solver.window_rows();
        let first = solver.rows() - rows.len();
        let w = solver.params().graph.hidden_cost;
        let trace: Vec<RowEstimate> = bands.iter().map(|&(e, _)| e).collect();
        let (marks, contrasts) = self.stretch.marks_and_contrasts(first, rows, &trace);
        let (mut marks, mut contrasts) = (marks.into_iter(), contrasts.into_iter());
        let inputs: Vec<evidence::RowInputs<'_>> = bands
            .iter()
            .map(|&(e, band)| {
                let (marked, contrast) = match e.reference {
                    Some(_) => (
                        marks.next().unwrap_or(false),
                        Some(contrasts.next().unwrap_or(0.0)),
                    ),
                    None => (false, None),
                };
                evidence::RowInputs {
                    row: e.row,
                    reference: e.reference,
                    relocalized: e.relocalized,
                    band,
                    contrast,
                    marked,
                    chat: &rows[e.row - first],
                    spread: self.stretch.spread(e.row),
                }
            })
            .collect();
        let evidence = evidence::window_evidence(
            &inputs,
            self.stretch.len(),
            &self.prior_rel,
            w,
            self.params.confidence.radius,
        );
        bands
            .into_iter()
            .zip(inputs.iter().map(|i| i.marked))
            .zip(evidence)
            .map(|(((e, band), marked), ev)| match e.reference {
                Some(_) if marked => (
                    RowEstimate {
                        reference: None,
                        ..e
                    },
                    0.0,
                    ev,
                ),
                Some(_) => (e, band.map_or(0.0, |b| b.ratio()), ev),
                None => (e, 0.0, ev),
            })
            .collect()
    }

    /// The best path over the lag window with each matched row's confidence (the discounted
    /// ratio on the frames so far; 0 for a hidden row).
    #[cfg(test)]
    fn window_ratios(&self) -> Vec<(RowEstimate, f64)> {
        self.window_bands()
            .into_iter()
            .map(|(e, b)| (e, b.map_or(0.0, |b| b.ratio())))
            .collect()
    }

    /// The best path over the lag window with each matched row's band costs (the discounted
    /// readout on the frames so far; `None` for a hidden row).
    fn window_bands(&self) -> Vec<(RowEstimate, Option<crate::confidence::BandCosts>)> {
        let Some(solver) = &self.solver else {
            return Vec::new();
        };
        let trace = solver.trace();
        let rows: Vec<&[f32]> = solver.window_rows().iter().map(Vec::as_slice).collect();
        let first = solver.rows() - rows.len();
        let targets: Vec<(usize, usize)> = trace
            .iter()
            .filter_map(|e| e.reference.map(|j| (e.row - first, j)))
            .collect();
        let bands = self.discount(solver.params().graph).window_bands(
            &rows,
            self.disc.0.as_deref(),
            &targets,
        );
        let mut bands = bands.into_iter();
        trace
            .into_iter()
            .map(|e| {
                let band = match e.reference {
                    Some(_) => bands.next().flatten(),
                    None => None,
                };
                (e, band)
            })
            .collect()
    }

    /// A frame's answer: its estimate with `p_correct` and status read from its evidence
    /// ([`crate::calibration`]).
    fn estimate(
        &self,
        frame: usize,
        reference: Option<usize>,
        confidence: f64,
        evidence: Option<&FrameEvidence>,
    ) -> FrameEstimate {
        let (p_correct, status) = match evidence {
            Some(ev) => {
                let p = if reference.is_some() {
                    calibration::trip_p_correct(ev, self.params.tolerance)
                } else {
                    0.0
                };
                let settle = self.stretch.len();
                let status =
                    calibration::frame_status(reference, p, ev, self.params.threshold, settle);
                (p, status)
            }
            None => (0.0, FrameStatus::Lost),
        };
        FrameEstimate {
            frame,
            reference,
            confidence,
            p_correct,
            status,
        }
    }

    /// Extends the trip by a batch of raw cosine rows (one per new frame, one column per map
    /// image). Validates the whole batch before changing any state.
    pub fn push_batch(&mut self, c: &Matrix) -> Result<BatchUpdate> {
        if c.rows() == 0 {
            return Err(Error::Empty("the batch has no frames".into()));
        }
        if c.cols() != self.prior.len() {
            return Err(Error::Shape(format!(
                "the batch has {} columns, the map has {} references",
                c.cols(),
                self.prior.len()
            )));
        }
        c.check_finite("similarity batch")?;
        let sums_before = self.sums.clone();
        let chat = self.normalize_batch(c);
        if let Err(e) = chat.check_finite("normalised similarity batch") {
            self.sums = sums_before;
            return Err(e);
        }
        if self.solver.is_none() {
            let w = self
                .params
                .hidden_cost
                .unwrap_or_else(|| auto_hidden_cost(&chat));
            let params = OnlineParams {
                graph: GraphParams {
                    fan_out: self.params.fan_out,
                    horizontal: self.params.horizontal,
                    hidden_cost: w,
                },
                lag: self.params.lag,
                relocalization: self.params.relocalization,
            };
            self.solver = Some(OnlineSolver::new(self.prior.len(), params)?);
        }
        let first_new = self.frames;
        let mut found: Vec<Option<(RowEstimate, f64)>> = vec![None; c.rows()];
        let mut found_evidence: Vec<Option<FrameEvidence>> = vec![None; c.rows()];
        let mut window = Vec::new();
        // Chunks of at most `lag` frames: each frame is traced while in the window.
        let mut start = 0;
        while start < c.rows() {
            let end = (start + self.params.lag).min(c.rows());
            for k in start..end {
                self.push_row(c.row(k), chat.row(k).to_vec())?;
            }
            window = self.score_window();
            for &(e, conf, ev) in &window {
                if e.row >= first_new {
                    found[e.row - first_new] = Some((e, conf));
                    found_evidence[e.row - first_new] = Some(ev);
                }
            }
            start = end;
        }
        let estimates: Vec<FrameEstimate> = found
            .iter()
            .zip(&found_evidence)
            .enumerate()
            .map(|(k, (f, ev))| {
                self.estimate(
                    first_new + k,
                    f.and_then(|(e, _)| e.reference),
                    f.map_or(0.0, |(_, conf)| conf),
                    ev.as_ref(),
                )
            })
            .collect();
        let latest = estimates
            .last()
            .copied()
            .ok_or_else(|| Error::Empty("the batch has no frames".into()))?;
        let jumped = found.iter().flatten().any(|(e, _)| e.relocalized);
        let status = if jumped {
            TripStatus::Relocalized
        } else if latest.status == FrameStatus::Localized {
            TripStatus::Localized
        } else {
            TripStatus::Lost
        };
        if self.log.is_some() {
            for (k, row) in c.iter_rows().enumerate() {
                self.pending
                    .log
                    .push(((first_new + k) as u64, persist::encode_row(row)));
            }
        }
        self.update_snapshot();
        let mut last_evidence: Vec<FrameEvidence> = window.iter().map(|w| w.2).collect();
        let window_first = last_evidence.first().map_or(usize::MAX, |e| e.frame);
        last_evidence.extend(
            found_evidence
                .into_iter()
                .flatten()
                .filter(|e| e.frame < window_first),
        );
        last_evidence.sort_by_key(|e| e.frame);
        self.last_evidence = last_evidence;
        let window = window
            .into_iter()
            .map(|(e, conf, ev)| self.estimate(e.row, e.reference, conf, Some(&ev)))
            .collect();
        Ok(BatchUpdate {
            estimates,
            window,
            status,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::confidence::ConfidenceParams;

    /// A deterministic raw cosine batch: frame `i` resembles reference `i % d` most.
    pub(crate) fn batch(first: usize, n: usize, d: usize, seed: u32) -> Matrix {
        let mut m = Matrix::zeros(n, d);
        for k in 0..n {
            let i = first + k;
            for j in 0..d {
                let noise = ((i * 31 + j * 17 + seed as usize) % 23) as f32 / 100.0;
                let peak = if j == i % d { 0.5 } else { 0.0 };
                m.set(k, j, 0.3 + noise + peak);
            }
        }
        m
    }

    #[test]
    fn the_lag_window_is_bounded_by_the_maps_size() {
        let with_lag = |lag| TripParams {
            lag,
            ..TripParams::default()
        };
        // 30,790 references (the paper's map): lag 544 fits, 545 does not.
        let d = 30_790;
        assert!(Trip::new(prior(d), with_lag(544)).is_ok());
        match Trip::new(prior(d), with_lag(545)) {
            Err(Error::Inconsistent { name, reason }) => {
                assert_eq!(name, "lag");
                assert!(reason.contains("at most 544"), "{reason}");
            }
            other => panic!("expected the lag refused, got {:?}", other.err()),
        }
        // The largest lag on a small map.
        assert!(Trip::new(prior(1_000), with_lag(10_000)).is_ok());
    }

    #[test]
    fn every_estimate_carries_p_correct_and_the_status_read_from_it() {
        let d = 30;
        let mut localized = 0;
        for threshold in [0.9, 1.0] {
            let params = TripParams {
                threshold,
                ..TripParams::default()
            };
            let wide = TripParams {
                tolerance: 3,
                ..params
            };
            let (mut trip, mut loose) = (
                Trip::new(prior(d), params).unwrap(),
                Trip::new(prior(d), wide).unwrap(),
            );
            for b in 0..8 {
                let u = trip.push_batch(&batch(b * 10, 10, d, 1)).unwrap();
                let v = loose.push_batch(&batch(b * 10, 10, d, 1)).unwrap();
                let seen: Vec<usize> = trip.last_evidence().iter().map(|e| e.frame).collect();
                for (e, w) in u
                    .estimates
                    .iter()
                    .chain(&u.window)
                    .zip(v.estimates.iter().chain(&v.window))
                {
                    assert!((0.0..=1.0).contains(&e.p_correct), "{e:?}");
                    assert!(seen.contains(&e.frame), "no evidence for {e:?}");
                    match e.reference {
                        None => {
                            assert_eq!(e.p_correct, 0.0);
                            assert!(matches!(e.status, FrameStatus::OffMap | FrameStatus::Lost));
                        }
                        Some(_) => {
                            assert_eq!(
                                e.status == FrameStatus::Localized,
                                e.p_correct >= threshold
                            );
                            localized += usize::from(e.status == FrameStatus::Localized);
                        }
                    }
                    // The same estimate at a larger tolerance is at least as probable.
                    assert_eq!((e.frame, e.reference), (w.frame, w.reference));
                    assert!(w.p_correct >= e.p_correct, "{e:?} vs {w:?}");
                }
                assert_eq!(u.latest_status(), u.estimates.last().unwrap().status);
            }
        }
        // The generated route is easy: the default threshold localizes most frames.
        assert!(localized > 100, "{localized}");
        let bad = |p: TripParams| Trip::new(prior(d), p).err().unwrap().to_string();
        assert!(bad(TripParams {
            threshold: 0.0,
            ..TripParams::default()
        })
        .contains("threshold"));
        assert!(bad(TripParams {
            threshold: 1.5,
            ..TripParams::default()
        })
        .contains("threshold"));
        assert!(bad(TripParams {
            tolerance: 5000,
            ..TripParams::default()
        })
        .contains("tolerance"));
    }

    pub(super) fn prior(d: usize) -> Vec<f32> {
        (0..d).map(|j| 0.4 + (j % 5) as f32 / 50.0).collect()
    }

    #[test]
    fn normalize_false_feeds_raw_rows_and_params_are_validated() {
        let d = 10;
        let raw = TripParams {
            normalize: false,
            hidden_cost: Some(1.5),
            relocalization: None,
            ..TripParams::default()
        };
        let mut trip = Trip::new(prior(d), raw).unwrap();
        let u = trip.push_batch(&batch(0, 4, d, 0)).unwrap();
        assert_eq!(u.estimates.len(), 4);
        assert_eq!(trip.hidden_cost(), Some(1.5));
        let bad = |p: TripParams| Trip::new(prior(d), p).err().unwrap().to_string();
        assert!(bad(TripParams { lag: 0, ..raw }).contains("lag"));
        assert!(bad(TripParams {
            fan_out: 5000,
            ..raw
        })
        .contains("fan_out"));
        assert!(bad(TripParams {
            prior_weight: -1.0,
            ..raw
        })
        .contains("prior_weight"));
        assert!(bad(TripParams {
            relocalization: Some(-2.0),
            ..raw
        })
        .contains("relocalization"));
        assert!(bad(TripParams {
            confidence: ConfidenceParams {
                discount: Some(1.0),
                ..raw.confidence
            },
            ..raw
        })
        .contains("discount"));
        assert!(trip.push_batch(&Matrix::zeros(0, d)).is_err());
        assert!(matches!(
            trip.push_batch(&Matrix::zeros(2, d + 1)),
            Err(Error::Shape(_))
        ));
        assert_eq!(trip.frames(), 4);
    }
}

#[cfg(test)]
mod confidence_tests {
    use super::*;
    use crate::confidence::ConfidenceParams;
    use crate::confidence::{chance_contrast, chance_marks, row_contrast, score_hypothesis};
    use crate::solver::{Hypothesis, Match, RowAssignment};
    use proptest::prelude::*;

    /// The offline discounted ratio of row `i` at `j` on `chat` (a hypothesis that matches
    /// only that row; the ratio of a row does not depend on the others).
    fn offline(
        chat: &Matrix,
        graph: &GraphParams,
        params: &ConfidenceParams,
        i: usize,
        j: usize,
    ) -> f64 {
        let rows = (0..chat.rows())
            .map(|q| RowAssignment {
                query: q,
                matches: if q == i {
                    vec![Match {
                        reference: j,
                        similarity: chat.get(i, j),
                    }]
                } else {
                    Vec::new()
                },
            })
            .collect();
        let h = Hypothesis {
            rank: 1,
            cost: 0.0,
            rows,
        };
        let scored = score_hypothesis(chat, graph, &h, params).unwrap();
        assert_eq!(scored.len(), 1);
        scored[0].confidence
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// After every batch, every frame the trip reports (its new frames and the re-traced
        /// lag window) carries the offline discounted ratio computed on the frames so far (up
        /// to the offline sweep's f32 rounding); for the newest frame that is the forward pass alone (its backward part is
        /// empty). Raw rows (no online normalisation) so the offline matrix is the same `ĉ`.
        #[test]
        fn trip_confidence_is_the_offline_discounted_ratio_of_the_prefix(
            d in 1usize..9, vals in prop::collection::vec(-0.2f32..3.0, 200),
            sizes in prop::collection::vec(1usize..6, 1..6),
            k in 0usize..4, horizontal: bool, w in 0.3f64..2.5, lag in 1usize..6,
            reloc in prop::option::of(0.0f64..3.0), g in 0.3f64..0.95, r in 0usize..3,
        ) {
            let q: usize = sizes.iter().sum();
            prop_assume!(q * d <= vals.len());
            let chat = Matrix::from_vec(q, d, vals[..q * d].to_vec()).unwrap();
            let params = TripParams {
                fan_out: k,
                horizontal,
                hidden_cost: Some(w),
                lag,
                relocalization: reloc,
                normalize: false,
                confidence: ConfidenceParams { half_window: 5, radius: r, discount: Some(g) },
                ..TripParams::default()
            };
            let graph = GraphParams { fan_out: k, horizontal, hidden_cost: w };
            let mut trip = Trip::new(vec![1.0; d], params).unwrap();
            let mut start = 0;
            for n in sizes {
                let rows: Vec<&[f32]> = (start..start + n).map(|i| chat.row(i)).collect();
                let u = trip.push_batch(&Matrix::from_rows(&rows).unwrap()).unwrap();
                start += n;
                let prefix = Matrix::from_vec(start, d, chat.as_slice()[..start * d].to_vec()).unwrap();
                // The ratios before the stretch rule hides any frame (`window_ratios`): what
                // the batch reported, except frames the rule put off the map (its own test
                // below).
                let ratios: Vec<FrameEstimate> = trip
                    .window_ratios()
                    .into_iter()
                    .map(|(e, conf)| FrameEstimate {
                        frame: e.row,
                        reference: e.reference,
                        confidence: conf,
                        p_correct: 0.0,
                        status: FrameStatus::Lost,
                    })
                    .collect();
                prop_assert_eq!(ratios.len(), u.window.len());
                for (a, b) in ratios.iter().zip(&u.window) {
                    let same = (a.frame, a.reference, a.confidence) == (b.frame, b.reference, b.confidence);
                    prop_assert!(same || (a.reference.is_some() && b.reference.is_none() && b.confidence == 0.0),
                        "{:?} vs {:?}", a, b);
                }
                let window_frames: Vec<usize> = ratios.iter().map(|e| e.frame).collect();
                for e in ratios.iter().chain(u.estimates.iter().filter(|e| !window_frames.contains(&e.frame))) {
                    match e.reference {
                        Some(j) if window_frames.contains(&e.frame) => {
                            // The trip's passes are f64, the offline sweep's f32 lanes
                            // (`confidence/sweep.rs`): equal up to that rounding, the
                            // tolerance of the offline sweep's own brute-force test.
                            let want = offline(&prefix, &graph, &params.confidence, e.frame, j);
                            prop_assert!((e.confidence - want).abs() <= 1e-5 * want.abs().max(1.0),
                                "frame {} of {}: {} vs {}", e.frame, start, e.confidence, want);
                        }
                        Some(_) => {} // left the window within this batch: scored on an earlier prefix
                        None => prop_assert_eq!(e.confidence, 0.0),
                    }
                }
            }
        }

        /// After every batch, the frames of the lag window the trip reports without a
        /// reference though its path matches them are exactly those the offline stretch rule
        /// marks on the window's matched frames: [`chance_marks`] of [`row_contrast`] at each
        /// match, with the trip's `L` and the chance bar of its `K`. Raw rows, so `ĉ` is `c`.
        #[test]
        fn trip_hides_the_frames_the_offline_stretch_rule_marks_on_its_window(
            d in 3usize..24, vals in prop::collection::vec(0.0f32..1.0, 24 * 60),
            sizes in prop::collection::vec(1usize..12, 1..7),
            k in 0usize..5, w in 0.5f64..3.0, lag in 1usize..40,
            reloc in prop::option::of(0.2f64..3.0), g in 0.5f64..0.9,
        ) {
            let q: usize = sizes.iter().sum();
            let chat = Matrix::from_vec(q, d, vals[..q * d].to_vec()).unwrap();
            let params = TripParams {
                fan_out: k,
                hidden_cost: Some(w),
                lag,
                relocalization: reloc,
                normalize: false,
                confidence: ConfidenceParams { discount: Some(g), ..ConfidenceParams::default() },
                ..TripParams::default()
            };
            let len = params.confidence.stretch_len();
            let bar = chance_contrast(k + 1);
            let mut trip = Trip::new(vec![1.0; d], params).unwrap();
            let mut start = 0;
            let mut scratch = Vec::new();
            for n in sizes {
                let rows: Vec<&[f32]> = (start..start + n).map(|i| chat.row(i)).collect();
                let u = trip.push_batch(&Matrix::from_rows(&rows).unwrap()).unwrap();
                start += n;
                let path: Vec<(usize, Option<usize>)> = trip
                    .window_ratios()
                    .into_iter()
                    .map(|(e, _)| (e.row, e.reference))
                    .collect();
                let matched: Vec<(usize, usize)> =
                    path.iter().filter_map(|&(i, j)| j.map(|j| (i, j))).collect();
                let contrast: Vec<f64> = matched
                    .iter()
                    .map(|&(i, j)| row_contrast(chat.row(i), j, &mut scratch))
                    .collect();
                let mut want = chance_marks(&contrast, len, bar).into_iter();
                prop_assert_eq!(path.len(), u.window.len());
                for (&(i, j), e) in path.iter().zip(&u.window) {
                    prop_assert_eq!(e.frame, i);
                    if j.is_some() {
                        let hidden = want.next().unwrap();
                        prop_assert_eq!(e.reference.is_none(), hidden, "frame {} of {}", i, start);
                    } else {
                        prop_assert!(e.reference.is_none());
                    }
                }
            }
        }
    }
}
