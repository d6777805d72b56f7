//! What a trip knows about each frame of its lag window besides its estimate: the evidence a
//! calibrated `p_correct` is computed from ([`crate::calibration`]).
//!
//! Everything here is a function of the trip's state after a batch (the re-traced lag window,
//! its `ĉ` rows, the discounted passes, the map's prior), never of earlier batches' answers, so
//! a restored trip (which replays its log row by row, `storage.rs`) reports the same evidence
//! as the live one.

pub use crate::calibration::FrameEvidence;
use crate::confidence::{BandCosts, RowSpread};

/// The inputs of [`window_evidence`] for one window row.
pub(super) struct RowInputs<'a> {
    pub row: usize,
    pub reference: Option<usize>,
    pub relocalized: bool,
    pub band: Option<BandCosts>,
    pub contrast: Option<f64>,
    pub marked: bool,
    pub chat: &'a [f32],
    pub spread: Option<RowSpread>,
}

/// The evidence of every row of the window (`rows` in order, the newest last); `len` is the
/// stretch length `L`, `prior` the map's prior divided by its median, `w` the hidden cost and
/// `radius` the confidence's band radius `r`.
pub(super) fn window_evidence(
    rows: &[RowInputs<'_>],
    len: usize,
    prior: &[f32],
    w: f64,
    radius: usize,
) -> Vec<FrameEvidence> {
    let n = rows.len();
    let newest = rows.last().map_or(0, |r| r.row);
    let len = len.max(1);
    // Matched rows in order: (index in rows, contrast, reference).
    let matched: Vec<(usize, f64, usize)> = rows
        .iter()
        .enumerate()
        .filter_map(|(k, r)| r.reference.map(|j| (k, r.contrast.unwrap_or(0.0), j)))
        .collect();
    let counted = |x: f64| {
        if x.is_nan() {
            0.0
        } else {
            x.clamp(-crate::confidence::STRONG, crate::confidence::STRONG)
        }
    };
    // Mean contrast of each stretch of `len` consecutive matched rows, by its first entry.
    let means: Vec<f64> = if matched.len() >= len {
        (0..=matched.len() - len)
            .map(|s| {
                matched[s..s + len]
                    .iter()
                    .map(|m| counted(m.1))
                    .sum::<f64>()
                    / len as f64
            })
            .collect()
    } else {
        Vec::new()
    };
    let ratios: Vec<f64> = matched
        .iter()
        .map(|m| rows[m.0].band.map_or(0.0, |b| b.ratio()))
        .collect();
    // The `len` matched entries nearest entry `t`: centred, shifted at the window's ends.
    let local = |t: usize| -> (usize, usize) {
        let k = len.min(matched.len());
        let a = t.saturating_sub(k / 2).min(matched.len() - k);
        (a, a + k)
    };
    let mut out = Vec::with_capacity(n);
    let mut dwell = 0usize;
    let mut prev_ref: Option<usize> = None;
    let mut last_jump: Option<usize> = None;
    let mut m = 0; // index into matched of the next matched row
    for (k, r) in rows.iter().enumerate() {
        if r.relocalized {
            last_jump = Some(k);
        }
        let since_jump = last_jump.map_or(n, |j| k - j);
        let hidden_trailing = rows[k.saturating_sub(len - 1)..=k]
            .iter()
            .filter(|r| r.reference.is_none())
            .count();
        // Matched rows up to and including this one.
        while m < matched.len() && matched[m].0 <= k {
            m += 1;
        }
        let this = r.reference.map(|_| m - 1);
        dwell = match (r.reference, prev_ref) {
            (Some(j), Some(p)) if j == p => dwell + 1,
            (Some(_), _) => 1,
            (None, _) => 0,
        };
        prev_ref = r.reference;
        let (stretch_local, ratio_before, ratio_after, log_ratio_local) = match this {
            Some(t) => {
                let (a, b) = local(t);
                let z = matched[a..b].iter().map(|m| counted(m.1)).sum::<f64>() / (b - a) as f64;
                let lr =
                    ratios[a..b].iter().map(|&x| x.max(1e-9).ln()).sum::<f64>() / (b - a) as f64;
                let max = |s: &[f64]| {
                    if s.is_empty() {
                        f64::NAN
                    } else {
                        s.iter().copied().fold(f64::NEG_INFINITY, f64::max)
                    }
                };
                let before = max(&ratios[t.saturating_sub(len)..t]);
                let after = max(&ratios[t + 1..(t + 1 + len).min(ratios.len())]);
                (z, before, after, lr)
            }
            None => (f64::NAN, f64::NAN, f64::NAN, f64::NAN),
        };
        let (stretch_trailing, stretch_min) = match this {
            Some(t) => {
                let trailing = if t + 1 >= len {
                    means[t + 1 - len]
                } else {
                    f64::NAN
                };
                let lo = (t + 1).saturating_sub(len);
                let hi = t.min(means.len().saturating_sub(1));
                let min = if means.is_empty() || lo > hi {
                    f64::NAN
                } else {
                    means[lo..=hi].iter().copied().fold(f64::INFINITY, f64::min)
                };
                (trailing, min)
            }
            None => (f64::NAN, f64::NAN),
        };
        // Advances of the path over its last `len` matched rows ending at this one.
        let upto = m;
        let from = upto.saturating_sub(len);
        let steps: Vec<f64> = matched[from..upto]
            .windows(2)
            .map(|p| {
                let (a, b) = (p[0], p[1]);
                let rows_apart = (rows[b.0].row - rows[a.0].row) as f64;
                (b.2 as f64 - a.2 as f64) / rows_apart
            })
            .collect();
        let (step_mean, step_spread) = if steps.is_empty() {
            (f64::NAN, f64::NAN)
        } else {
            let mean = steps.iter().sum::<f64>() / steps.len() as f64;
            let mut s = steps.clone();
            s.sort_by(f64::total_cmp);
            let med = s[s.len() / 2];
            let spread = steps.iter().map(|x| (x - med).abs()).sum::<f64>() / steps.len() as f64;
            (mean, spread)
        };
        let (chat, chat_of_best, best_offset, prior_at, stake) = match r.reference {
            Some(j) => {
                let v = f64::from(r.chat[j]);
                let (bj, bv) =
                    r.chat
                        .iter()
                        .enumerate()
                        .fold((0usize, f32::NEG_INFINITY), |acc, (i, &x)| {
                            if x > acc.1 {
                                (i, x)
                            } else {
                                acc
                            }
                        });
                let node = crate::confidence::best_node_cost(r.chat, j, radius);
                (
                    v,
                    if bv > 0.0 { v / f64::from(bv) } else { 0.0 },
                    bj.abs_diff(j),
                    f64::from(prior.get(j).copied().unwrap_or(0.0)),
                    w - node,
                )
            }
            None => (0.0, 0.0, 0, 0.0, f64::NAN),
        };
        let (ratio, hidden_ratio) = match r.band {
            Some(b) if r.reference.is_some() => (
                b.ratio(),
                if b.inside.is_finite() && b.inside > 0.0 {
                    b.hidden / b.inside
                } else {
                    f64::INFINITY
                },
            ),
            _ => (0.0, f64::NAN),
        };
        out.push(FrameEvidence {
            frame: r.row,
            path_reference: r.reference,
            ratio,
            hidden_ratio,
            stake,
            contrast: r.contrast.unwrap_or(0.0),
            stretch_trailing,
            stretch_min,
            marked: r.marked,
            later: newest - r.row,
            since_jump,
            hidden_trailing,
            step_mean,
            step_spread,
            chat,
            chat_of_best,
            best_offset,
            prior: prior_at,
            hidden_cost: w,
            stretch_local,
            ratio_before,
            ratio_after,
            log_ratio_local,
            dwell,
            row_scale: r.spread.map_or(f64::NAN, |s| s.scale()),
            row_median: r.spread.map_or(f64::NAN, |s| s.median()),
        });
    }
    out
}
