//! The stored form of a trip (format 2), and the format-1 blob of earlier versions.
//!
//! Format 1 was one blob per trip, rewritten whole by every batch: the prior, the running sums,
//! the solver's cost rows and its lag window of back-pointers and `ĉ` rows, about
//! `(28 + 12·lag) · D` bytes (1 MB at `lag` 32 on 2,400 references, 13 MB on 30,790). Most of
//! it never changes (the prior) or is derived from the rows (the window), so format 2 keeps
//! three parts, each written only when it changes:
//!
//! | part | bytes | written |
//! | --- | --- | --- |
//! | **base** (magic `SLTB`): parameters, the prior column means | `4·D` | once, at open |
//! | **snapshot** (magic `SLTS`): the trip at the start of its lag window: frame count, normalisation sums, solver cost rows (empty window), discounted forward value | `32·D` | when due: the first batch (`W` resolved), then once the log holds `2·lag` rows |
//! | **log**: one raw cosine row per frame since the snapshot, keyed by frame | `4·D` each | every batch: its frames' rows; rows before a new snapshot are dropped with it |
//!
//! [`super::Trip::restore`] replays the log on the snapshot with the batch's own row steps
//! (normalisation, solver, window base), which is deterministic, so the restored trip is the
//! live one bit for bit; at most `2·lag` + one batch of rows are replayed. A trip continued
//! from a format-1 blob has no window base (format 1 did not keep one): it is stored with a
//! snapshot of mode *full image* (the solver's lag window included) rewritten per batch, and
//! no log. Every part is little-endian, floats bit-exact ([`super::state`]); every count and
//! invariant is checked on decode, so corrupt bytes are an error, never a panic.

use std::collections::VecDeque;

use crate::confidence::ConfidenceParams;

use super::confidence::DiscountedForward;
use super::normalize::Sums;
use super::online::OnlineSolver;
use super::state::{corrupt_state, StateReader, StateWriter, STATE_FORMAT};
use super::{LogWindow, Stored, Trip, TripParams};
use crate::Result;

/// Magic of a format-1 blob.
const LEGACY_MAGIC: &[u8; 4] = b"SLTR";
/// Magic of a base.
const BASE_MAGIC: &[u8; 4] = b"SLTB";
/// Magic of a snapshot.
const SNAPSHOT_MAGIC: &[u8; 4] = b"SLTS";
/// The format-1 version byte.
const LEGACY_FORMAT: u8 = 1;
/// Snapshot mode: the trip at the start of its lag window (a log follows).
const MODE_WINDOW_BASE: u8 = 0;
/// Snapshot mode: the whole trip, lag window included (continued from format 1; no log).
const MODE_FULL_IMAGE: u8 = 1;

/// A trip's stored form written from scratch ([`super::Trip::stored_state`]).
#[derive(Clone, Debug, PartialEq)]
pub struct StoredState {
    /// Parameters and prior; never changes.
    pub base: Vec<u8>,
    /// The latest snapshot.
    pub snapshot: Vec<u8>,
    /// Raw rows after the snapshot, `(frame, bytes)`, in frame order.
    pub log: Vec<(u64, Vec<u8>)>,
}

/// What the batches since the last [`super::Trip::take_delta`] change in the stored form.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StateDelta {
    /// A base to write (only for a trip read from a format-1 blob, which had none); it
    /// replaces that blob.
    pub base: Option<Vec<u8>>,
    /// A new snapshot, replacing the stored one.
    pub snapshot: Option<Vec<u8>>,
    /// New log rows, `(frame, bytes)`, in frame order.
    pub log: Vec<(u64, Vec<u8>)>,
    /// Log rows of frames below this one are dropped (written with `snapshot`).
    pub drop_log_before: Option<u64>,
}

impl StateDelta {
    /// Bytes of the parts to write.
    pub fn bytes(&self) -> usize {
        self.base.as_ref().map_or(0, Vec::len)
            + self.snapshot.as_ref().map_or(0, Vec::len)
            + self.log.iter().map(|(_, r)| r.len()).sum::<usize>()
    }

    pub(super) fn heap_bytes(&self) -> usize {
        self.base.as_ref().map_or(0, Vec::capacity)
            + self.snapshot.as_ref().map_or(0, Vec::capacity)
            + self.log.iter().map(|(_, r)| r.capacity()).sum::<usize>()
    }
}

fn write_params(w: &mut StateWriter, p: &TripParams) {
    w.u64(p.fan_out as u64);
    w.bool(p.horizontal);
    w.opt_f64(p.hidden_cost);
    w.u64(p.lag as u64);
    w.opt_f64(p.relocalization);
    w.f64(p.prior_weight);
    w.bool(p.normalize);
    w.u64(p.confidence.half_window as u64);
    w.u64(p.confidence.radius as u64);
}

fn read_params(r: &mut StateReader<'_>) -> Result<TripParams> {
    Ok(TripParams {
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
            discount: None,
        },
        ..TripParams::default()
    })
}

/// Reads the magic and format byte of a part.
fn header(r: &mut StateReader<'_>, magic: &[u8; 4], format: u8, what: &str) -> Result<()> {
    if r.take(4)? != magic {
        return Err(corrupt_state(format!("not a trip {what} (bad magic)")));
    }
    let found = r.u8()?;
    if found != format {
        return Err(corrupt_state(format!(
            "{what} format {found} is not supported (this build reads {format})"
        )));
    }
    Ok(())
}

/// The trip's base: parameters and prior.
pub(super) fn encode_base(t: &Trip) -> Vec<u8> {
    let mut w = StateWriter::new();
    w.raw(BASE_MAGIC);
    w.u8(STATE_FORMAT);
    write_params(&mut w, &t.params);
    w.opt_f64(t.params.confidence.discount);
    w.u64(t.prior.len() as u64);
    w.f32s(&t.prior);
    // Trailer (since the calibration): tolerance and threshold. A base without it (written
    // before) reads with the defaults.
    w.u64(t.params.tolerance as u64);
    w.f64(t.params.threshold);
    w.into_bytes()
}

/// A trip with no frames from its base.
pub(super) fn decode_base(bytes: &[u8]) -> Result<Trip> {
    let mut r = StateReader::new(bytes);
    header(&mut r, BASE_MAGIC, STATE_FORMAT, "base")?;
    let mut params = read_params(&mut r)?;
    params.confidence.discount = r.opt_f64()?;
    let d = r.usize()?;
    if r.remaining() / 4 < d {
        return Err(corrupt_state(format!(
            "base is truncated: {d} columns announced"
        )));
    }
    let prior = r.f32s(d)?;
    if r.remaining() > 0 {
        params.tolerance = r.usize()?;
        params.threshold = r.f64()?;
    }
    r.finish()?;
    Trip::new(prior, params).map_err(|e| corrupt_state(format!("base: {e}")))
}

fn write_tail(w: &mut StateWriter, solver: Option<&OnlineSolver>, disc: &DiscountedForward) {
    match solver {
        None => w.u8(0),
        Some(s) => {
            w.u8(1);
            s.encode(w);
        }
    }
    match &disc.0 {
        None => w.u8(0),
        Some(m) => {
            w.u8(1);
            w.f64s(m);
        }
    }
}

/// The snapshot at the start of the lag window (mode [`MODE_WINDOW_BASE`]).
pub(super) fn encode_base_image(t: &Trip) -> Vec<u8> {
    let mut w = StateWriter::new();
    w.raw(SNAPSHOT_MAGIC);
    w.u8(STATE_FORMAT);
    w.u8(MODE_WINDOW_BASE);
    let (raw_len, base) = match &t.log {
        Some(l) => (l.raw.len(), &l.base),
        None => (0, &t.sums),
    };
    w.u64((t.frames - raw_len) as u64);
    w.f64s(&base.columns);
    w.f64(base.similarity);
    let solver = t.solver.as_ref().and_then(OnlineSolver::base_image);
    write_tail(&mut w, solver.as_ref(), &t.disc);
    w.into_bytes()
}

/// The whole trip, lag window included (mode [`MODE_FULL_IMAGE`]).
pub(super) fn encode_full_image(t: &Trip) -> Vec<u8> {
    let mut w = StateWriter::new();
    w.raw(SNAPSHOT_MAGIC);
    w.u8(STATE_FORMAT);
    w.u8(MODE_FULL_IMAGE);
    w.u64(t.frames as u64);
    w.f64s(&t.sums.columns);
    w.f64(t.sums.similarity);
    write_tail(&mut w, t.solver.as_ref(), &t.disc);
    w.into_bytes()
}

/// Sets `t` (fresh from its base) to the snapshot, checking it against the base.
pub(super) fn decode_snapshot(t: &mut Trip, bytes: &[u8]) -> Result<()> {
    let d = t.prior.len();
    let mut r = StateReader::new(bytes);
    header(&mut r, SNAPSHOT_MAGIC, STATE_FORMAT, "snapshot")?;
    let mode = r.u8()?;
    if mode != MODE_WINDOW_BASE && mode != MODE_FULL_IMAGE {
        return Err(corrupt_state(format!("bad snapshot mode {mode}")));
    }
    let frames = r.usize()?;
    if r.remaining() / 8 < d {
        return Err(corrupt_state("snapshot is truncated"));
    }
    let sums = Sums {
        columns: r.f64s(d)?,
        similarity: r.f64()?,
    };
    let solver = match r.u8()? {
        0 => None,
        1 => Some(OnlineSolver::decode(&mut r)?),
        t => return Err(corrupt_state(format!("bad solver tag {t}"))),
    };
    let disc = match r.u8()? {
        0 => DiscountedForward(None),
        1 => DiscountedForward(Some(r.f64s(d)?)),
        t => return Err(corrupt_state(format!("bad forward-value tag {t}"))),
    };
    r.finish()?;
    check_solver(t, solver.as_ref(), frames)?;
    if let Some(s) = &solver {
        let window = s.window_rows().len();
        if mode == MODE_WINDOW_BASE && window != 0 {
            return Err(corrupt_state("a window-base snapshot with a lag window"));
        }
        // The discounted value exists exactly when rows left the window (format 2).
        if mode == MODE_WINDOW_BASE && disc.0.is_some() != (frames > 0) {
            return Err(corrupt_state(
                "the discounted forward value does not fit the frames",
            ));
        }
    } else if disc.0.is_some() {
        return Err(corrupt_state("a discounted forward value without a solver"));
    }
    t.frames = frames;
    t.solver = solver;
    t.disc = disc;
    if mode == MODE_WINDOW_BASE {
        t.log = Some(LogWindow {
            raw: VecDeque::new(),
            base: sums.clone(),
        });
    } else {
        t.log = None;
    }
    t.stored = Stored {
        snapshot_row: frames,
        snapshot_has_solver: t.solver.is_some(),
        base_written: true,
    };
    t.sums = sums;
    Ok(())
}

/// The solver must fit the trip: as many rows as frames, the trip's width and parameters.
fn check_solver(t: &Trip, solver: Option<&OnlineSolver>, frames: usize) -> Result<()> {
    let d = t.prior.len();
    match solver {
        None if frames != 0 => Err(corrupt_state("frames were consumed but there is no solver")),
        Some(s) if s.rows() != frames || s.references() != d => Err(corrupt_state(format!(
            "the solver has {} rows and {} columns, the trip {frames} frames and {d} references",
            s.rows(),
            s.references(),
        ))),
        Some(s)
            if s.params().lag != t.params.lag
                || s.params().graph.fan_out != t.params.fan_out
                || s.params().graph.horizontal != t.params.horizontal
                || s.params().relocalization != t.params.relocalization
                || t.params
                    .hidden_cost
                    .is_some_and(|w| w != s.params().graph.hidden_cost) =>
        {
            Err(corrupt_state(
                "the solver's parameters differ from the trip's",
            ))
        }
        _ => Ok(()),
    }
}

/// One log row: the frame's raw cosine row, `D` little-endian `f32`.
pub(super) fn encode_row(row: &[f32]) -> Vec<u8> {
    let mut out = Vec::with_capacity(row.len() * 4);
    for v in row {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Reads a log row of `d` values.
pub(super) fn decode_row(bytes: &[u8], d: usize) -> Result<Vec<f32>> {
    if bytes.len() != d * 4 {
        return Err(corrupt_state(format!(
            "a log row of {} bytes for {d} references",
            bytes.len()
        )));
    }
    Ok(bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect())
}

/// Reads a format-1 blob (magic `SLTR`).
pub(super) fn decode_legacy(bytes: &[u8]) -> Result<Trip> {
    let mut r = StateReader::new(bytes);
    header(&mut r, LEGACY_MAGIC, LEGACY_FORMAT, "state")?;
    // Format 1 scored with the box window of half-width L; its discounted equivalent is
    // g = 1 - 1/(L+1) (`TripParams::discount` with no explicit discount).
    let params = read_params(&mut r)?;
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
    trip.sums.columns = r.f64s(d)?;
    trip.sums.similarity = r.f64()?;
    let frames = r.usize()?;
    // The box window's recent rows: not needed by the discounted confidence.
    let recent = r.usize()?;
    if recent > params.confidence.half_window || recent > frames {
        return Err(corrupt_state(format!(
            "{recent} recent rows for a confidence window of {}",
            params.confidence.half_window
        )));
    }
    for _ in 0..recent {
        r.f32s(d)?;
    }
    let solver = match r.u8()? {
        0 => None,
        1 => Some(OnlineSolver::decode(&mut r)?),
        t => return Err(corrupt_state(format!("bad solver tag {t}"))),
    };
    r.finish()?;
    check_solver(&trip, solver.as_ref(), frames)?;
    trip.frames = frames;
    trip.solver = solver;
    if frames > 0 {
        // No window base: full images from now on.
        trip.log = None;
    }
    trip.stored = Stored {
        snapshot_row: frames,
        snapshot_has_solver: trip.solver.is_some(),
        base_written: false,
    };
    Ok(trip)
}

/// Everything in memory, for bit-identity checks (see [`Trip::image_bytes`]).
pub(super) fn encode_image_for_comparison(t: &Trip) -> Vec<u8> {
    let mut out = encode_base(t);
    let mut w = StateWriter::new();
    w.f64(t.prior_mean);
    w.u64(t.stored.snapshot_row as u64);
    w.bool(t.stored.snapshot_has_solver);
    w.bool(t.stored.base_written);
    out.extend(w.into_bytes());
    out.extend(encode_full_image(t));
    if let Some(log) = &t.log {
        out.extend(encode_base_image(t));
        for r in &log.raw {
            out.extend(encode_row(r));
        }
    }
    out
}
