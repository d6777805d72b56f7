//! The trip's side of its stored form ([`super::persist`] owns the bytes): after each batch,
//! whether a new snapshot is due and what the store must write ([`Trip::take_delta`]); the
//! stored form written from scratch ([`Trip::stored_state`]); and [`Trip::restore`], which
//! replays the log on the snapshot with the batch's own row steps so a restored trip is the
//! live one bit for bit. Apart from the driver because it is the one place that knows when
//! and what to persist, and its tests (a store's semantics, corrupt states) are its own.

use super::normalize::{NormScratch, Prior};
use super::{persist, state, StateDelta, Stored, StoredState, Trip};
use crate::Result;

impl Trip {
    /// After a batch: decides whether the store needs a new snapshot (see [`persist`]).
    pub(super) fn update_snapshot(&mut self) {
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
    /// trip that wrote them. Corrupt or foreign bytes are an [`crate::Error::Format`] naming the
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
    use super::super::tests::{batch, prior};
    use super::*;
    use crate::trip::TripParams;
    use crate::Error;
    use std::collections::BTreeMap;

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
    fn the_base_keeps_tolerance_and_threshold_and_an_older_base_reads_with_the_defaults() {
        let d = 12;
        let params = TripParams {
            tolerance: 3,
            threshold: 0.8,
            ..TripParams::default()
        };
        let trip = Trip::new(prior(d), params).unwrap();
        let base = trip.stored_state().base;
        let read = super::super::persist::decode_base(&base).unwrap();
        assert_eq!((read.params.tolerance, read.params.threshold), (3, 0.8));
        // A base written before the calibration ends at the prior (no trailer).
        let older = &base[..base.len() - 16];
        let read = super::super::persist::decode_base(older).unwrap();
        let d = TripParams::default();
        assert_eq!(
            (read.params.tolerance, read.params.threshold),
            (d.tolerance, d.threshold)
        );
        // A trailer cut short is corrupt, not a default.
        assert!(super::super::persist::decode_base(&base[..base.len() - 4]).is_err());
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

    #[test]
    fn state_size_is_bounded_by_the_lag_window_not_the_trip_length() {
        // The README's "State per trip": the trip's heap and its stored form (written from
        // scratch) depend on `lag` and `D`, not on how many frames the trip has seen.
        let d = 30;
        let params = TripParams::default();
        let mut trip = Trip::new(prior(d), params).unwrap();
        let (mut heap, mut stored) = (Vec::new(), Vec::new());
        for b in 0..100 {
            trip.push_batch(&batch(b * 10, 10, d, 2)).unwrap();
            // As the service does after each batch's write.
            trip.take_delta();
            heap.push(trip.heap_bytes());
            let s = trip.stored_state();
            stored.push(
                s.base.len() + s.snapshot.len() + s.log.iter().map(|(_, r)| r.len()).sum::<usize>(),
            );
        }
        assert_eq!(trip.frames(), 1000);
        // The log cycles between `lag` and `2·lag` rows (32 and 64 here): once the window has
        // filled, batches 8..24 (160 frames, several cycles) reach every size the state has.
        for sizes in [&heap, &stored] {
            let cycle = *sizes[8..24].iter().max().unwrap();
            assert!(sizes[24..].iter().all(|&s| s <= cycle), "{sizes:?}");
        }
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
}
