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
//!   the frames so far ([`confidence`]): causal at arrival (the forward pass alone, the scored
//!   frame last), re-scored with the later frames while it stays in the lag window. Its cost
//!   per batch is `2 · lag` row steps, whatever the trip's length.
//! * **Status** of the latest frame: `lost` when it is hidden or its confidence is at most
//!   [`LOST_RATIO`] (no local evidence for the match), `relocalized` when the best path entered
//!   one of this batch's frames by a relocalization jump, else `localized`.
//! * **Stored form** ([`persist`]): a constant *base* (parameters and prior, written once), a
//!   *snapshot* of the trip at the start of its lag window, and a *log* of the raw rows since
//!   the snapshot. A batch writes its raw rows (`4 · D` bytes per frame) and, once every `lag`
//!   frames, a new snapshot (`O(D)`): [`Trip::take_delta`]. [`Trip::restore`] replays the log
//!   on the snapshot with the same row steps, so a restored trip is bit-identical to the live
//!   one.

use std::collections::VecDeque;

use crate::confidence::{ConfidenceParams, GraphParams, DEFAULT_DISCOUNT};
use crate::solver::{auto_hidden_cost, check_fan_out, check_hidden_cost};
use crate::{Error, Matrix, Result};

mod confidence;
mod normalize;
pub mod online;
pub mod persist;
pub mod state;

use confidence::{Discount, DiscountedForward};
pub use normalize::column_prior;
use normalize::{NormScratch, Prior, Sums};
use online::{OnlineParams, OnlineSolver, RowEstimate};
pub use persist::{StateDelta, StoredState};

/// A latest frame whose confidence is at most this is reported as lost.
pub const LOST_RATIO: f64 = 1.0;

/// Largest accepted confidence half window `L` and radius `r`.
pub const MAX_CONFIDENCE_WINDOW: usize = 1000;

/// Parameters of a trip.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TripParams {
    /// Fan-out `K`.
    pub fan_out: usize,
    /// Horizontal edges.
    pub horizontal: bool,
    /// `W`, or `None` to resolve it from the first batch.
    pub hidden_cost: Option<f64>,
    /// Rows whose back-pointers are kept (older estimates are final).
    pub lag: usize,
    /// Cost `R` of re-entering the map anywhere; `None` disables relocalization.
    pub relocalization: Option<f64>,
    /// Frames' worth of weight given to the map's prior column means.
    pub prior_weight: f64,
    /// Online column normalisation (Eq. 2 with the map prior); `false` uses raw cosine rows.
    pub normalize: bool,
    /// The confidence: radius `r` and discount `g` (`None`: `g = 1 - 1/(L+1)` from the half
    /// window `L`, as the offline default relates them).
    pub confidence: ConfidenceParams,
}

impl TripParams {
    /// Checks every parameter's range, without a map: the graph (fan-out cap, `W`) with the
    /// solver's one check ([`crate::solver::check_fan_out`], [`crate::solver::check_hidden_cost`]),
    /// the lag window and relocalization cost, the prior weight and the confidence.
    pub fn validate(&self) -> Result<()> {
        if !(self.prior_weight.is_finite() && self.prior_weight >= 0.0) {
            return Err(Error::param(
                "prior_weight",
                format!("must be a finite number >= 0, got {}", self.prior_weight),
            ));
        }
        check_fan_out(self.fan_out)?;
        if let Some(w) = self.hidden_cost {
            check_hidden_cost(w)?;
        }
        online::check_window(self.lag, self.relocalization)?;
        if self.confidence.half_window > MAX_CONFIDENCE_WINDOW
            || self.confidence.radius > MAX_CONFIDENCE_WINDOW
        {
            return Err(Error::param(
                "confidence",
                format!(
                    "half window and radius must be at most {MAX_CONFIDENCE_WINDOW}, got {:?}",
                    self.confidence
                ),
            ));
        }
        let g = self.discount();
        if !(g > 0.0 && g < 1.0) {
            return Err(Error::param(
                "discount",
                format!("must be within (0, 1), got {g}"),
            ));
        }
        Ok(())
    }

    /// The discount `g` the trip scores with (see [`TripParams::confidence`]).
    pub fn discount(&self) -> f64 {
        self.confidence
            .discount
            .unwrap_or(1.0 - 1.0 / (self.confidence.half_window as f64 + 1.0))
    }
}

impl Default for TripParams {
    fn default() -> Self {
        TripParams {
            fan_out: 4,
            horizontal: true,
            hidden_cost: None,
            lag: 32,
            relocalization: Some(DEFAULT_RELOCALIZATION_COST),
            prior_weight: 100.0,
            normalize: true,
            confidence: ConfidenceParams {
                discount: Some(DEFAULT_DISCOUNT),
                ..ConfidenceParams::default()
            },
        }
    }
}

/// Default relocalization cost `R`, in units of summed node costs.
pub const DEFAULT_RELOCALIZATION_COST: f64 = 1.0;

/// A trip's answer for one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameEstimate {
    /// Frame index since the trip started.
    pub frame: usize,
    /// Estimated reference index, `None` when not on the map (hidden).
    pub reference: Option<usize>,
    /// The discounted min-marginal ratio on the frames so far (0 when hidden): causal for the
    /// newest frame, re-scored with the later frames for the others (see [`confidence`]).
    pub confidence: f64,
}

/// Where the trip stands after a batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TripStatus {
    /// The latest frame is matched with local support.
    Localized,
    /// The latest frame is hidden or has no local support.
    Lost,
    /// The path re-entered the map by a jump during this batch.
    Relocalized,
}

/// The result of one batch.
#[derive(Clone, Debug, PartialEq)]
pub struct BatchUpdate {
    /// One estimate per new frame, as seen at the end of the batch (or, in a batch longer
    /// than the lag window, when the frame was last in the window).
    pub estimates: Vec<FrameEstimate>,
    /// The best path over the lag window (older frames first), re-traced with this batch.
    pub window: Vec<FrameEstimate>,
    /// The trip's status after the batch.
    pub status: TripStatus,
}

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
}

impl Trip {
    /// A trip on a map whose prior column means are `prior` (see [`column_prior`]).
    pub fn new(prior: Vec<f32>, params: TripParams) -> Result<Self> {
        if prior.is_empty() {
            return Err(Error::Empty("the map has no reference images".into()));
        }
        params.validate()?;
        let d = prior.len();
        let prior_mean = prior.iter().map(|v| f64::from(*v)).sum::<f64>() / d as f64;
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
        })
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

    /// The best path over the lag window with each matched row's confidence.
    fn score_window(&self) -> Vec<(RowEstimate, f64)> {
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
        let ratios = self.discount(solver.params().graph).window_ratios(
            &rows,
            self.disc.0.as_deref(),
            &targets,
        );
        let mut ratios = ratios.into_iter();
        trace
            .into_iter()
            .map(|e| {
                let conf = match e.reference {
                    Some(_) => ratios.next().unwrap_or(0.0),
                    None => 0.0,
                };
                (e, conf)
            })
            .collect()
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
        let mut window = Vec::new();
        // Chunks of at most `lag` frames: each frame is traced while in the window.
        let mut start = 0;
        while start < c.rows() {
            let end = (start + self.params.lag).min(c.rows());
            for k in start..end {
                self.push_row(c.row(k), chat.row(k).to_vec())?;
            }
            window = self.score_window();
            for &(e, conf) in &window {
                if e.row >= first_new {
                    found[e.row - first_new] = Some((e, conf));
                }
            }
            start = end;
        }
        let estimates: Vec<FrameEstimate> = found
            .iter()
            .enumerate()
            .map(|(k, f)| FrameEstimate {
                frame: first_new + k,
                reference: f.and_then(|(e, _)| e.reference),
                confidence: f.map_or(0.0, |(_, conf)| conf),
            })
            .collect();
        let latest = estimates
            .last()
            .copied()
            .ok_or_else(|| Error::Empty("the batch has no frames".into()))?;
        let jumped = found.iter().flatten().any(|(e, _)| e.relocalized);
        let status = if latest.reference.is_none() || latest.confidence <= LOST_RATIO {
            TripStatus::Lost
        } else if jumped {
            TripStatus::Relocalized
        } else {
            TripStatus::Localized
        };
        if self.log.is_some() {
            for (k, row) in c.iter_rows().enumerate() {
                self.pending
                    .log
                    .push(((first_new + k) as u64, persist::encode_row(row)));
            }
        }
        self.update_snapshot();
        let window = window
            .into_iter()
            .map(|(e, conf)| FrameEstimate {
                frame: e.row,
                reference: e.reference,
                confidence: conf,
            })
            .collect();
        Ok(BatchUpdate {
            estimates,
            window,
            status,
        })
    }

    /// After a batch: decides whether the store needs a new snapshot (see [`persist`]).
    fn update_snapshot(&mut self) {
        if !self.stored.base_written {
            self.pending.base = Some(persist::encode_base(self));
        }
        let Some(log) = &self.log else {
            // A trip continued from format 1 has no window base: a full image per batch.
            self.pending.snapshot = Some(persist::encode_full_image(self));
            self.stored = Stored {
                snapshot_row: self.frames,
                snapshot_has_solver: self.solver.is_some(),
                base_written: true,
            };
            return;
        };
        let has_solver = self.solver.is_some();
        let due = !self.stored.base_written
            || (has_solver && !self.stored.snapshot_has_solver)
            || self.frames - self.stored.snapshot_row >= 2 * self.params.lag;
        if !due {
            return;
        }
        let row = self.frames - log.raw.len();
        self.pending.snapshot = Some(persist::encode_base_image(self));
        self.pending.drop_log_before = Some(row as u64);
        self.pending.log.retain(|(f, _)| *f >= row as u64);
        self.stored = Stored {
            snapshot_row: row,
            snapshot_has_solver: has_solver,
            base_written: true,
        };
    }

    /// What the store must write for the batches pushed since the last call: the new log
    /// rows, and a new snapshot (with the log rows before it to drop) when one is due. A
    /// store that applies every delta in order, each atomically, holds what
    /// [`Trip::restore`] needs. The delta of a batch is `4 · D` bytes per frame plus, once
    /// every `lag` frames, a snapshot of `O(D)` (a trip continued from format 1 writes a full
    /// image per batch instead).
    pub fn take_delta(&mut self) -> StateDelta {
        std::mem::take(&mut self.pending)
    }

    /// The stored form of this trip written from scratch (a new trip's, at open): the base,
    /// a snapshot at the start of the lag window and the window's raw rows as the log.
    pub fn stored_state(&self) -> StoredState {
        match &self.log {
            Some(log) => StoredState {
                base: persist::encode_base(self),
                snapshot: persist::encode_base_image(self),
                log: log
                    .raw
                    .iter()
                    .enumerate()
                    .map(|(k, r)| {
                        (
                            (self.frames - log.raw.len() + k) as u64,
                            persist::encode_row(r),
                        )
                    })
                    .collect(),
            },
            None => StoredState {
                base: persist::encode_base(self),
                snapshot: persist::encode_full_image(self),
                log: Vec::new(),
            },
        }
    }

    /// Restores a trip from its stored form: the base, the snapshot, and the log rows from
    /// the snapshot's frame on (in order, as `(frame, bytes)`), for a trip of `frames` frames
    /// (the record's count: a log that does not reach it is corrupt). The rows are replayed
    /// with the same row steps as [`Trip::push_batch`], so the result is bit-identical to the
    /// trip that wrote them. Corrupt or foreign bytes are an [`Error::Format`] naming the
    /// trip state, never a panic.
    pub fn restore(
        base: &[u8],
        snapshot: &[u8],
        log: &[(u64, &[u8])],
        frames: u64,
    ) -> Result<Self> {
        let mut trip = persist::decode_base(base)?;
        persist::decode_snapshot(&mut trip, snapshot)?;
        let start = trip.frames as u64;
        if start + log.len() as u64 != frames {
            return Err(state::corrupt_state(format!(
                "the snapshot is at frame {start} and the log has {} rows; the trip has {frames} frames",
                log.len()
            )));
        }
        if trip.log.is_none() && !log.is_empty() {
            return Err(state::corrupt_state("a full image followed by log rows"));
        }
        let d = trip.prior.len();
        let mut scratch = NormScratch::default();
        let mut chat = vec![0.0f32; d];
        for (k, (frame, bytes)) in log.iter().enumerate() {
            if *frame != start + k as u64 {
                return Err(state::corrupt_state(format!(
                    "log row {frame} where frame {} was expected",
                    start + k as u64
                )));
            }
            let raw = persist::decode_row(bytes, d)?;
            if let Some(j) = raw.iter().position(|v| !v.is_finite()) {
                return Err(state::corrupt_state(format!(
                    "log row {frame} has a non-finite value at column {j}"
                )));
            }
            if trip.params.normalize {
                let prior = Prior {
                    means: &trip.prior,
                    mean: trip.prior_mean,
                    weight: trip.params.prior_weight,
                };
                prior.normalize_row(
                    &mut trip.sums,
                    trip.frames + 1,
                    &raw,
                    &mut chat,
                    &mut scratch,
                );
            } else {
                chat.copy_from_slice(&raw);
            }
            trip.push_row(&raw, chat.clone())
                .map_err(|e| state::corrupt_state(format!("log row {frame}: {e}")))?;
        }
        Ok(trip)
    }

    /// Restores a trip from a format-1 state (one blob, written by versions before the
    /// stored form of [`persist`]). Its solver continues exactly; its confidence starts its
    /// discounted forward pass at the stored lag window (format 1 kept no earlier rows: the
    /// evidence dropped weighs at most `g^lag`, 0.003 at the defaults). It keeps writing a
    /// full image per batch ([`Trip::take_delta`]), unless it had no frames yet.
    pub fn from_legacy_bytes(bytes: &[u8]) -> Result<Self> {
        persist::decode_legacy(bytes)
    }

    /// The exact in-memory state as bytes, for bit-identity checks (not a stored format):
    /// base, full image, window base, raw window rows and the store bookkeeping.
    pub fn image_bytes(&self) -> Vec<u8> {
        persist::encode_image_for_comparison(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

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

    fn prior(d: usize) -> Vec<f32> {
        (0..d).map(|j| 0.4 + (j % 5) as f32 / 50.0).collect()
    }

    /// What a store holds after applying every delta in order (the engines' semantics).
    #[derive(Default)]
    struct Held {
        base: Vec<u8>,
        snapshot: Vec<u8>,
        log: BTreeMap<u64, Vec<u8>>,
    }

    impl Held {
        fn new(s: StoredState) -> Self {
            Held {
                base: s.base,
                snapshot: s.snapshot,
                log: s.log.into_iter().collect(),
            }
        }
        fn apply(&mut self, d: StateDelta) {
            if let Some(b) = d.base {
                self.base = b;
            }
            if let Some(s) = d.snapshot {
                self.snapshot = s;
            }
            if let Some(before) = d.drop_log_before {
                self.log.retain(|f, _| *f >= before);
            }
            self.log.extend(d.log);
        }
        fn restore(&self, frames: usize) -> Result<Trip> {
            let log: Vec<(u64, &[u8])> = self.log.iter().map(|(f, r)| (*f, &r[..])).collect();
            Trip::restore(&self.base, &self.snapshot, &log, frames as u64)
        }
        fn bytes(&self) -> usize {
            self.base.len() + self.snapshot.len() + self.log.values().map(Vec::len).sum::<usize>()
        }
    }

    #[test]
    fn a_restored_trip_continues_bit_identically() {
        let d = 40;
        for params in [
            TripParams {
                lag: 8,
                ..TripParams::default()
            },
            TripParams {
                lag: 3,
                normalize: false,
                hidden_cost: Some(1.2),
                relocalization: None,
                ..TripParams::default()
            },
        ] {
            let mut live = Trip::new(prior(d), params).unwrap();
            let mut held = Held::new(live.stored_state());
            // The state before the first batch round-trips too.
            let fresh = held.restore(0).unwrap();
            assert_eq!(fresh.image_bytes(), live.image_bytes());
            // Batches of varying size, some longer than the lag window.
            for (b, n) in [7usize, 1, 12, 3, 9, 1, 1, 20, 5, 2, 8]
                .into_iter()
                .enumerate()
            {
                let m = batch(live.frames(), n, d, 1);
                let mut restored = held.restore(live.frames()).unwrap();
                assert_eq!(
                    restored.image_bytes(),
                    live.image_bytes(),
                    "before batch {b}"
                );
                let a = live.push_batch(&m).unwrap();
                let r = restored.push_batch(&m).unwrap();
                assert_eq!(a, r, "batch {b}");
                // Bit-identical: every float of the state, and the same delta to write.
                assert_eq!(live.image_bytes(), restored.image_bytes(), "batch {b}");
                let delta = live.take_delta();
                assert_eq!(delta, restored.take_delta(), "batch {b}");
                held.apply(delta);
            }
        }
    }

    #[test]
    fn a_batch_writes_its_rows_and_a_snapshot_once_in_a_while_not_the_window() {
        let d = 30;
        let params = TripParams::default();
        let mut trip = Trip::new(prior(d), params).unwrap();
        let mut held = Held::new(trip.stored_state());
        let mut snapshots = 0;
        let mut stored_sizes = Vec::new();
        for b in 0..60 {
            trip.push_batch(&batch(b * 10, 10, d, 2)).unwrap();
            let delta = trip.take_delta();
            // Always the batch's raw rows; a snapshot (O(D), no window) when due.
            assert_eq!(delta.log.len(), 10);
            assert!(delta.log.iter().all(|(_, r)| r.len() == 4 * d));
            if let Some(s) = &delta.snapshot {
                snapshots += 1;
                assert!(s.len() < 40 * d + 200, "{}", s.len());
            }
            assert!(delta.base.is_none());
            held.apply(delta);
            stored_sizes.push(held.bytes());
            // The log never holds more than 2·lag rows plus one batch.
            assert!(held.log.len() < 2 * params.lag + 10, "{}", held.log.len());
        }
        // First batch (W resolved), then one every 2·lag - lag = 32..=40 frames.
        assert!((14..=20).contains(&snapshots), "{snapshots}");
        // The stored form stays bounded, whatever the trip's length.
        let max = *stored_sizes.iter().max().unwrap();
        assert!(
            stored_sizes[10..].iter().all(|&s| s * 2 > max),
            "{stored_sizes:?}"
        );
        assert_eq!(trip.frames(), 600);
        assert_eq!(held.restore(600).unwrap().image_bytes(), trip.image_bytes());
    }

    /// A format-1 blob of `t` as the previous versions wrote it (`SLTR`, format byte 1).
    fn legacy_blob(t: &Trip) -> Vec<u8> {
        let mut w = state::StateWriter::new();
        w.raw(b"SLTR");
        w.u8(1);
        let p = &t.params;
        w.u64(p.fan_out as u64);
        w.bool(p.horizontal);
        w.opt_f64(p.hidden_cost);
        w.u64(p.lag as u64);
        w.opt_f64(p.relocalization);
        w.f64(p.prior_weight);
        w.bool(p.normalize);
        w.u64(p.confidence.half_window as u64);
        w.u64(p.confidence.radius as u64);
        w.u64(t.prior.len() as u64);
        w.f32s(&t.prior);
        w.f64(t.prior_mean);
        w.f64s(&t.sums.columns);
        w.f64(t.sums.similarity);
        w.u64(t.frames as u64);
        // One recent row of the box window (ignored now).
        let recent = t.frames.min(1);
        w.u64(recent as u64);
        for _ in 0..recent {
            w.f32s(&vec![0.5; t.prior.len()]);
        }
        match &t.solver {
            None => w.u8(0),
            Some(s) => {
                w.u8(1);
                s.encode(&mut w);
            }
        }
        w.into_bytes()
    }

    #[test]
    fn a_format_1_state_continues_and_is_stored_in_format_2() {
        let d = 25;
        let params = TripParams {
            lag: 40,
            ..TripParams::default()
        };
        let mut live = Trip::new(prior(d), params).unwrap();
        // Never driven: continues in the log form.
        let mut idle = Trip::from_legacy_bytes(&legacy_blob(&live)).unwrap();
        idle.push_batch(&batch(0, 3, d, 4)).unwrap();
        let delta = idle.take_delta();
        assert!(delta.base.is_some() && delta.snapshot.is_some());
        assert_eq!(delta.log.len(), 3);
        for b in 0..3 {
            live.push_batch(&batch(b * 6, 6, d, 4)).unwrap();
        }
        live.take_delta();
        let mut old = Trip::from_legacy_bytes(&legacy_blob(&live)).unwrap();
        let mut held = Held::default();
        for b in 3..12 {
            let m = batch(b * 6, 6, d, 4);
            let a = live.push_batch(&m).unwrap();
            let o = old.push_batch(&m).unwrap();
            // Same path; the confidences too while the window holds the whole trip (lag 40),
            // since the discounted forward pass then starts at the trip's first frame.
            if live.frames() <= params.lag {
                assert_eq!(a, o, "batch {b}");
            } else {
                assert_eq!(
                    a.estimates.iter().map(|e| e.reference).collect::<Vec<_>>(),
                    o.estimates.iter().map(|e| e.reference).collect::<Vec<_>>()
                );
            }
            let delta = old.take_delta();
            // The first delta writes the base; every one a full image and no log.
            assert_eq!(delta.base.is_some(), b == 3);
            assert!(delta.snapshot.is_some() && delta.log.is_empty());
            live.take_delta();
            held.apply(delta);
            let restored = held.restore(old.frames()).unwrap();
            assert_eq!(restored.image_bytes(), {
                // The store bookkeeping says the base is written now.
                old.image_bytes()
            });
        }
        let bad = legacy_blob(&live);
        assert!(matches!(
            Trip::from_legacy_bytes(&bad[..bad.len() - 3]),
            Err(Error::Format { .. })
        ));
        let mut version = bad.clone();
        version[4] = 99;
        let err = Trip::from_legacy_bytes(&version).err().unwrap();
        assert!(err.to_string().contains("format 99"), "{err}");
    }

    #[test]
    fn corrupt_states_are_errors_not_panics() {
        let d = 12;
        let params = TripParams {
            lag: 4,
            ..TripParams::default()
        };
        let mut trip = Trip::new(prior(d), params).unwrap();
        let mut held = Held::new(trip.stored_state());
        for b in 0..4 {
            trip.push_batch(&batch(b * 5, 5, d, 3)).unwrap();
            held.apply(trip.take_delta());
        }
        let frames = trip.frames();
        assert!(held.restore(frames).is_ok());
        let is_format = |r: Result<Trip>| matches!(r, Err(Error::Format { .. }));
        // Wrong frame count, missing or extra rows, truncated parts, bad magic.
        assert!(is_format(held.restore(frames + 1)));
        let log: Vec<(u64, &[u8])> = held.log.iter().map(|(f, r)| (*f, &r[..])).collect();
        let restore = |base: &[u8], snap: &[u8], log: &[(u64, &[u8])], n: usize| {
            Trip::restore(base, snap, log, n as u64)
        };
        assert!(is_format(restore(
            &held.base,
            &held.snapshot,
            &log[1..],
            frames - 1
        )));
        let mut gap = log.clone();
        gap[1].0 += 7;
        assert!(is_format(restore(&held.base, &held.snapshot, &gap, frames)));
        let mut short = log.clone();
        short[0].1 = &short[0].1[..5];
        assert!(is_format(restore(
            &held.base,
            &held.snapshot,
            &short,
            frames
        )));
        let nan = f32::NAN.to_le_bytes().repeat(d);
        let mut bad_row = log.clone();
        bad_row[0].1 = &nan;
        assert!(is_format(restore(
            &held.base,
            &held.snapshot,
            &bad_row,
            frames
        )));
        let (b, s) = (&held.base, &held.snapshot);
        assert!(is_format(restore(&b[..b.len() - 1], s, &log, frames)));
        assert!(is_format(restore(b, &s[..s.len() - 1], &log, frames)));
        assert!(is_format(restore(b"nope", s, &log, frames)));
        assert!(is_format(restore(b, b, &log, frames)));
        let mut version = s.clone();
        version[4] = 99;
        let err = restore(b, &version, &log, frames).err().unwrap();
        assert!(err.to_string().contains("format 99"), "{err}");
        // Flipping any single byte of either part never panics (it may still decode: floats
        // are free); neither does continuing the trip.
        for part in 0..2 {
            let bytes = if part == 0 { b } else { s };
            for k in 0..bytes.len() {
                let mut flipped = bytes.clone();
                flipped[k] ^= 0xa5;
                let (b2, s2) = if part == 0 {
                    (&flipped, s)
                } else {
                    (b, &flipped)
                };
                let _ =
                    restore(b2, s2, &log, frames).map(|mut t| t.push_batch(&batch(20, 3, d, 3)));
            }
        }
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
    use crate::confidence::score_hypothesis;
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
                let window_frames: Vec<usize> = u.window.iter().map(|e| e.frame).collect();
                for e in u.window.iter().chain(u.estimates.iter().filter(|e| !window_frames.contains(&e.frame))) {
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
    }
}
