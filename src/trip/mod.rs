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
//!   reference cannot get an exploding `ĉ`. On the Nordland dev split, streamed in batches of
//!   10 frames, a frame's estimate scores AP 0.78 at arrival and 0.82 after the lag window,
//!   against 0.85 offline (README, Trips).
//! * **Hidden cost.** `auto` resolves `W` once, from the first batch's normalised rows, with the
//!   same quantile rule as offline ([`crate::solver::auto_hidden_cost`]), and keeps it for the
//!   trip so the path costs stay comparable.
//! * **The path** is [`online::OnlineSolver`] (O(D) per frame, back-pointers for a lag
//!   window, optional relocalization).
//! * **Confidence** of a frame is the local min-marginal ratio ([`crate::confidence`]) on the
//!   `L` rows before it and the rows after it that have arrived (at most `L`).
//! * **Status** of the latest frame: `lost` when it is hidden or its confidence is at most
//!   [`LOST_RATIO`] (no local evidence for the match), `relocalized` when the best path entered
//!   one of this batch's frames by a relocalization jump, else `localized`.

use std::collections::VecDeque;

use crate::confidence::{window_ratio, ConfidenceParams, GraphParams};
use crate::solver::{auto_hidden_cost, check_fan_out, check_hidden_cost};
use crate::{Error, Matrix, Result};

mod normalize;
pub mod online;
pub mod state;

pub use normalize::column_prior;
use online::{OnlineParams, OnlineSolver, RowEstimate};
use state::{corrupt_state, StateReader, StateWriter, STATE_FORMAT};

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
    /// Confidence window and radius.
    pub confidence: ConfidenceParams,
}

impl TripParams {
    /// Checks every parameter's range, without a map: the graph (fan-out cap, `W`) with the
    /// solver's one check ([`crate::solver::check_fan_out`], [`crate::solver::check_hidden_cost`]),
    /// the lag window and relocalization cost, the prior weight and the confidence window.
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
        Ok(())
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
            confidence: ConfidenceParams::window(),
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
    /// Local min-marginal ratio (0 when hidden): causal for a batch's new frames (the rows before
    /// it and those of its batch after it); for earlier frames re-traced in the lag window, over
    /// the rows around it that the window holds.
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
    /// One estimate per new frame, as seen at the end of the batch.
    pub estimates: Vec<FrameEstimate>,
    /// The best path over the lag window (older frames first), re-traced with this batch.
    pub window: Vec<FrameEstimate>,
    /// The trip's status after the batch.
    pub status: TripStatus,
}

/// Magic bytes at the start of an encoded trip state.
const STATE_MAGIC: &[u8; 4] = b"SLTR";

/// One trip's bounded state.
#[derive(Clone)]
pub struct Trip {
    params: TripParams,
    prior: Vec<f32>,
    prior_mean: f64,
    column_sums: Vec<f64>,
    similarity_sum: f64,
    solver: Option<OnlineSolver>,
    /// The last `L` normalised rows before the current batch, for causal confidences.
    recent: VecDeque<Vec<f32>>,
    frames: usize,
}

impl Trip {
    /// A trip on a map whose prior column means are `prior` (see [`column_prior`]).
    pub fn new(prior: Vec<f32>, params: TripParams) -> Result<Self> {
        if prior.is_empty() {
            return Err(Error::Empty("the map has no reference images".into()));
        }
        params.validate()?;
        let prior_mean = prior.iter().map(|v| f64::from(*v)).sum::<f64>() / prior.len() as f64;
        Ok(Trip {
            params,
            column_sums: vec![0.0; prior.len()],
            prior,
            prior_mean,
            similarity_sum: 0.0,
            solver: None,
            recent: VecDeque::new(),
            frames: 0,
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

    /// The exact state as bytes (format [`STATE_FORMAT`], little-endian, bit-exact floats):
    /// a trip restored with [`Trip::from_bytes`] continues bit-identically. The size is
    /// `O((lag + L) · D)`, independent of the trip's length.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut w = StateWriter::new();
        w.raw(STATE_MAGIC);
        w.u8(STATE_FORMAT);
        let p = &self.params;
        w.u64(p.fan_out as u64);
        w.bool(p.horizontal);
        w.opt_f64(p.hidden_cost);
        w.u64(p.lag as u64);
        w.opt_f64(p.relocalization);
        w.f64(p.prior_weight);
        w.bool(p.normalize);
        w.u64(p.confidence.half_window as u64);
        w.u64(p.confidence.radius as u64);
        w.u64(self.prior.len() as u64);
        w.f32s(&self.prior);
        w.f64(self.prior_mean);
        w.f64s(&self.column_sums);
        w.f64(self.similarity_sum);
        w.u64(self.frames as u64);
        w.u64(self.recent.len() as u64);
        for row in &self.recent {
            w.f32s(row);
        }
        match &self.solver {
            None => w.u8(0),
            Some(s) => {
                w.u8(1);
                s.encode(&mut w);
            }
        }
        w.into_bytes()
    }

    /// Restores a trip from [`Trip::to_bytes`]. A corrupt or foreign state is an
    /// [`Error::Format`] that names the trip state, never a panic.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        let mut r = StateReader::new(bytes);
        if r.take(4)? != STATE_MAGIC {
            return Err(corrupt_state("not a trip state (bad magic)"));
        }
        let format = r.u8()?;
        if format != STATE_FORMAT {
            return Err(corrupt_state(format!(
                "state format {format} is not supported (this build reads {STATE_FORMAT})"
            )));
        }
        let params = TripParams {
            fan_out: r.usize()?,
            horizontal: r.bool()?,
            hidden_cost: r.opt_f64()?,
            lag: r.usize()?,
            relocalization: r.opt_f64()?,
            prior_weight: r.f64()?,
            normalize: r.bool()?,
            confidence: ConfidenceParams {
                half_window: r.usize()?,
                radius: r.usize()?,
                // Trips score with the causal box window (the discounted ratio is offline).
                discount: None,
            },
        };
        let d = r.usize()?;
        if r.remaining() / 12 < d {
            return Err(corrupt_state(format!(
                "state is truncated: {d} columns announced"
            )));
        }
        let prior = r.f32s(d)?;
        let mut trip =
            Trip::new(prior, params).map_err(|e| corrupt_state(format!("parameters: {e}")))?;
        trip.prior_mean = r.f64()?;
        trip.column_sums = r.f64s(d)?;
        trip.similarity_sum = r.f64()?;
        trip.frames = r.usize()?;
        let recent = r.usize()?;
        if recent > params.confidence.half_window || recent > trip.frames {
            return Err(corrupt_state(format!(
                "{recent} recent rows for a confidence window of {}",
                params.confidence.half_window
            )));
        }
        for _ in 0..recent {
            trip.recent.push_back(r.f32s(d)?);
        }
        trip.solver = match r.u8()? {
            0 => None,
            1 => Some(OnlineSolver::decode(&mut r)?),
            t => return Err(corrupt_state(format!("bad solver tag {t}"))),
        };
        match &trip.solver {
            None if trip.frames != 0 => {
                return Err(corrupt_state("frames were consumed but there is no solver"))
            }
            Some(s) if s.rows() != trip.frames || s.references() != d => {
                return Err(corrupt_state(format!(
                    "the solver has {} rows and {} columns, the trip {} frames and {d} references",
                    s.rows(),
                    s.references(),
                    trip.frames
                )))
            }
            _ => {}
        }
        r.finish()?;
        Ok(trip)
    }

    /// Approximate heap bytes held by this trip (vectors' capacities), for memory reports.
    pub fn heap_bytes(&self) -> usize {
        let recent: usize = self.recent.iter().map(|r| r.capacity() * 4).sum();
        self.prior.capacity() * 4
            + self.column_sums.capacity() * 8
            + recent
            + self.solver.as_ref().map_or(0, |s| s.heap_bytes())
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

        let chat = self.normalize(c);
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
        let solver = self.solver.as_mut().expect("created above");
        let first_new = self.frames;
        // Rows of this batch that already left the lag window (batches longer than `lag`).
        let mut committed = Vec::new();
        for row in chat.iter_rows() {
            if let Some(e) = solver.push_row(row)? {
                if e.row >= first_new {
                    committed.push(e);
                }
            }
        }
        let graph = solver.params().graph;
        self.frames += chat.rows();

        let solver = self.solver.as_ref().expect("created above");
        let trace = solver.trace();
        let scored: Vec<(RowEstimate, f64)> = committed
            .iter()
            .chain(&trace)
            .map(|e| {
                let conf = match e.reference {
                    Some(j) if e.row >= first_new => {
                        self.causal_confidence(&chat, e.row - first_new, j, &graph)
                    }
                    Some(j) => self.window_confidence(solver, e.row, j, &graph),
                    None => 0.0,
                };
                (*e, conf)
            })
            .collect();
        let by_row = |row: usize| scored.iter().find(|(e, _)| e.row == row);
        let estimates: Vec<FrameEstimate> = (first_new..self.frames)
            .map(|frame| match by_row(frame) {
                Some((e, conf)) => FrameEstimate {
                    frame,
                    reference: e.reference,
                    confidence: *conf,
                },
                None => FrameEstimate {
                    frame,
                    reference: None,
                    confidence: 0.0,
                },
            })
            .collect();
        let latest = estimates.last().copied().expect("batch is not empty");
        let jumped = scored
            .iter()
            .any(|(e, _)| e.row >= first_new && e.relocalized);
        let status = if latest.reference.is_none() || latest.confidence <= LOST_RATIO {
            TripStatus::Lost
        } else if jumped {
            TripStatus::Relocalized
        } else {
            TripStatus::Localized
        };

        let keep = self.params.confidence.half_window;
        for row in chat.iter_rows() {
            self.recent.push_back(row.to_vec());
            if self.recent.len() > keep {
                self.recent.pop_front();
            }
        }
        let window = scored[committed.len()..]
            .iter()
            .map(|(e, conf)| FrameEstimate {
                frame: e.row,
                reference: e.reference,
                confidence: *conf,
            })
            .collect();
        Ok(BatchUpdate {
            estimates,
            window,
            status,
        })
    }

    /// Local ratio of an earlier frame still in the lag window, re-traced at `j`: its `L` rows
    /// on each side as far as the window holds them (later frames have arrived since, so this
    /// sees more of its future than the confidence it was first reported with).
    fn window_confidence(
        &self,
        solver: &OnlineSolver,
        row: usize,
        j: usize,
        graph: &GraphParams,
    ) -> f64 {
        let window = solver.window_rows();
        let l = self.params.confidence.half_window;
        let idx = row + window.len() - solver.rows();
        let lo = idx.saturating_sub(l);
        let hi = (idx + l).min(window.len() - 1);
        let rows: Vec<&[f32]> = (lo..=hi).map(|t| window[t].as_slice()).collect();
        window_ratio(&rows, idx - lo, graph, self.params.confidence.radius, j)
    }

    /// Local ratio of frame `first_new + k` at `j`: the `L` rows before it (from earlier batches
    /// and this one) and at most `L` rows after it from this batch.
    fn causal_confidence(&self, batch: &Matrix, k: usize, j: usize, graph: &GraphParams) -> f64 {
        let l = self.params.confidence.half_window;
        let mut rows: Vec<&[f32]> = Vec::with_capacity(2 * l + 1);
        let from_batch_before = k.min(l);
        let from_recent = l - from_batch_before;
        let skip = self.recent.len().saturating_sub(from_recent);
        rows.extend(self.recent.iter().skip(skip).map(Vec::as_slice));
        let scored = rows.len() + from_batch_before;
        let last = (k + l).min(batch.rows() - 1);
        rows.extend((k - from_batch_before..=last).map(|t| batch.row(t)));
        window_ratio(&rows, scored, graph, self.params.confidence.radius, j)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic raw cosine batch: frame `i` resembles reference `i % d` most.
    fn batch(first: usize, n: usize, d: usize, seed: u32) -> Matrix {
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

    #[test]
    fn a_restored_trip_continues_bit_identically() {
        let d = 40;
        let params = TripParams {
            lag: 8,
            ..TripParams::default()
        };
        let mut live = Trip::new(prior(d), params).unwrap();
        // The state before the first batch round-trips too.
        let fresh = Trip::from_bytes(&live.to_bytes()).unwrap();
        assert_eq!(fresh.to_bytes(), live.to_bytes());
        for b in 0..3 {
            live.push_batch(&batch(b * 7, 7, d, 1)).unwrap();
        }
        let bytes = live.to_bytes();
        let mut restored = Trip::from_bytes(&bytes).unwrap();
        assert_eq!(restored.to_bytes(), bytes);
        for b in 3..9 {
            let m = batch(b * 7, 7, d, 1);
            let a = live.push_batch(&m).unwrap();
            let r = restored.push_batch(&m).unwrap();
            assert_eq!(a, r, "batch {b}");
            // Bit-identical: every float of the state, not only the answers.
            assert_eq!(live.to_bytes(), restored.to_bytes(), "batch {b}");
        }
    }

    #[test]
    fn state_size_is_bounded_by_the_lag_window_not_the_trip_length() {
        let d = 30;
        let mut trip = Trip::new(prior(d), TripParams::default()).unwrap();
        let mut sizes = Vec::new();
        for b in 0..30 {
            trip.push_batch(&batch(b * 10, 10, d, 2)).unwrap();
            sizes.push(trip.to_bytes().len());
        }
        // Once the lag window (32) and confidence rows (5) are full, the size is constant.
        let full = sizes[4];
        assert!(sizes[4..].iter().all(|&s| s == full), "{sizes:?}");
        assert_eq!(trip.frames(), 300);
    }

    #[test]
    fn corrupt_states_are_errors_not_panics() {
        let d = 12;
        let mut trip = Trip::new(prior(d), TripParams::default()).unwrap();
        trip.push_batch(&batch(0, 10, d, 3)).unwrap();
        let bytes = trip.to_bytes();
        let is_format = |r: Result<Trip>| matches!(r, Err(Error::Format { .. }));
        assert!(is_format(Trip::from_bytes(&bytes[..bytes.len() - 1])));
        assert!(is_format(Trip::from_bytes(b"nope")));
        let mut extra = bytes.clone();
        extra.push(0);
        assert!(is_format(Trip::from_bytes(&extra)));
        let mut version = bytes.clone();
        version[4] = 99;
        let err = Trip::from_bytes(&version).err().unwrap();
        assert!(err.to_string().contains("format 99"), "{err}");
        // Flipping any single byte never panics (it may still decode: floats are free).
        for k in 0..bytes.len() {
            let mut b = bytes.clone();
            b[k] ^= 0xa5;
            let _ = Trip::from_bytes(&b).map(|mut t| t.push_batch(&batch(10, 3, d, 3)));
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
        assert!(trip.push_batch(&Matrix::zeros(0, d)).is_err());
        assert!(matches!(
            trip.push_batch(&Matrix::zeros(2, d + 1)),
            Err(Error::Shape(_))
        ));
        assert_eq!(trip.frames(), 4);
    }
}
