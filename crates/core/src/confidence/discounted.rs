//! The discounted min-marginal ratio: the local ratio of [`super`] in `O(Q·D)` total.
//!
//! The box window of [`super::window_readout`] (rows `i-L ..= i+L`, free ends) has to be solved
//! anew for every scored row: `(2L+1)·D` work per row. Weighting the rows of a route by
//! `g^|t-i|` instead (`0 < g < 1`) keeps the same meaning — evidence near row `i` counts, far
//! evidence fades — but decomposes: with `FX_i`, `FH_i` the cheapest *discounted* path from the
//! source to a node of row `i` (row `t` weighted `g^(i-t)`), `FX_i[j] = c_ij + min(g·base_j,
//! FX_i[j-1])` where `base` is the sliding-window minimum of row `i-1`'s `min(FX, FH)`: the
//! solver's forward row step run on the previous row scaled by `g`. The backward values
//! `BX_i`, `BH_i` (row `t > i` weighted `g^(t-i)`, node excluded) are the backward step of
//! [`crate::solver::row_alternatives`] with the next row scaled by `g`. Then
//! `m(x_ij) = FX_i[j] + BX_i[j]` is the cheapest complete route through `x_ij` with every row
//! weighted by its distance to `i`, for every `i` at once: one forward and one backward pass.
//!
//! The ratio is the one of [`super`]: `outside / inside`, `inside` the best route through a
//! match within `r` of the prediction, `outside` the best through a match further away or a
//! hidden node of row `i`. `g = 1 - 1/(L+1)` gives the rows at distance `<= L` from `i` the bulk
//! of the weight, as the box window of half-width `L`. A property test checks the result
//! against every route of small graphs enumerated by brute force.
//!
//! Online (trips) the same statistic is causal with the backward part left out: `FX_i + 0`
//! (the forward pass alone, the scored frame last).
//!
//! Computed by [`super::sweep`]: one forward and one backward pass in `f32` lanes, running on
//! two threads and meeting in the middle (nothing recomputed); see there for the cost.

use crate::Matrix;

use super::sweep::{sweep, RowView};
use super::GraphParams;

/// How a scored row is read out of its min-marginals.
#[derive(Clone, Copy, Debug)]
pub(super) struct Readout {
    /// `r`: the confidence is the ratio with alternatives within `r` frames counted as the
    /// same place.
    pub radius: usize,
    /// `c`: the frames a prediction claims on each side. The prediction is the frame within
    /// `c` of the path's match whose `±c` neighbourhood the evidence supports best (the
    /// largest ratio at radius `c`); 0 keeps the path's match.
    pub claim: usize,
}

/// One scored row: the frame it names, its confidence, and whether the evidence puts it off
/// the map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Reading {
    /// The frame the prediction names (see [`Readout`]).
    pub at: usize,
    /// The ratio at radius `r` around `at`.
    pub confidence: f64,
    /// The row's own min-marginals put it off the map rather than at `at`
    /// ([`super::off_the_map`]).
    pub off_map: bool,
    /// The cheapest route hidden at the row over the cheapest through the band around `at`
    /// (`+inf` when no route passes the band; evidence for the calibration).
    pub hidden_ratio: f64,
}

/// Reads row `i` out for the path's match `j_star`: see [`Reading`] and [`Readout`]. `row` is
/// the row's `ĉ` and `w` the hidden cost (the off-the-map test, [`super::off_the_map`]).
pub(super) fn read(view: &RowView<'_>, ro: Readout, j_star: usize, row: &[f32], w: f64) -> Reading {
    let d = view.lay.d;
    // Every band the readout looks at lies within `span` of the match: keep those values,
    // and the best route anywhere else (or hidden).
    let span = ro.claim + ro.claim.max(ro.radius);
    let lo = j_star.saturating_sub(span);
    let hi = (j_star + span).min(d - 1);
    let near: Vec<f32> = (lo..=hi).map(|j| view.through(j)).collect();
    let far = view.best_outside(lo, hi).min(view.hidden);
    let band = Near {
        lo,
        near: &near,
        far,
    };
    let (at, confidence) = pick(&band, ro, j_star);
    let inside = band.band(at, ro.radius).0;
    Reading {
        at,
        confidence,
        hidden_ratio: if inside.is_finite() && inside > 0.0 {
            f64::from(view.hidden) / f64::from(inside)
        } else {
            f64::INFINITY
        },
        off_map: super::off_the_map(
            f64::from(view.hidden),
            f64::from(band.band(at, ro.radius).0),
            super::best_node_cost(row, at, ro.radius),
            w,
        ),
    }
}

/// The values of one row a readout looks at: `m(x_ij)` of the columns `lo ..` and the best
/// route through any other column or a hidden node.
struct Near<'a> {
    lo: usize,
    near: &'a [f32],
    far: f32,
}

/// `outside / inside` (0 when no route passes inside the band).
fn ratio_of(inside: f32, outside: f32) -> f64 {
    if inside.is_finite() {
        f64::from(outside) / f64::from(inside)
    } else {
        0.0
    }
}

impl Near<'_> {
    /// The cheapest route through a column within `r` of `centre` and the cheapest anywhere
    /// else or hidden, `(inside, outside)` (`+inf` when none), by one scan.
    fn band(&self, centre: usize, r: usize) -> (f32, f32) {
        let (a, b) = (centre.saturating_sub(r), centre + r);
        let (mut inside, mut outside) = (f32::INFINITY, self.far);
        for (j, &v) in (self.lo..).zip(self.near) {
            if (a..=b).contains(&j) {
                inside = inside.min(v);
            } else {
                outside = outside.min(v);
            }
        }
        (inside, outside)
    }

    /// The ratio with the columns within `r` of `centre` as the band.
    fn ratio(&self, centre: usize, r: usize) -> f64 {
        let (inside, outside) = self.band(centre, r);
        ratio_of(inside, outside)
    }
}

/// The prediction and confidence of [`read`] from the row's values: the claim's candidates
/// in `O(span)` (one sliding-window minimum for the bands, prefix and suffix minima for the
/// rest), not `O(claim · span)`, so a large `claim` (a large scoring tolerance) stays linear.
/// Minima are exact, so every ratio is the one [`Near::ratio`] computes (test
/// `the_linear_claim_readout_is_the_direct_one`).
fn pick(row: &Near<'_>, ro: Readout, j_star: usize) -> (usize, f64) {
    let (lo, near, c) = (row.lo, row.near, ro.claim);
    let hi = lo + near.len() - 1;
    let first = j_star.saturating_sub(c);
    let last = (j_star + c).min(hi);
    // pre[k] = min near[..k], suf[k] = min near[k..].
    let mut pre = Vec::with_capacity(near.len() + 1);
    pre.push(f32::INFINITY);
    for &v in near {
        pre.push(pre[pre.len() - 1].min(v));
    }
    let mut suf = vec![f32::INFINITY; near.len() + 1];
    for k in (0..near.len()).rev() {
        suf[k] = suf[k + 1].min(near[k]);
    }
    // Candidates in column order; both ends of their bands only move right: a monotone deque.
    let mut claimed = Vec::with_capacity(last + 1 - first);
    let mut deque = std::collections::VecDeque::new();
    let mut next = 0;
    for centre in first..=last {
        let a = centre.saturating_sub(c).max(lo) - lo;
        let b = (centre + c).min(hi) - lo;
        while next <= b {
            while deque.back().is_some_and(|&k: &usize| near[k] >= near[next]) {
                deque.pop_back();
            }
            deque.push_back(next);
            next += 1;
        }
        while deque.front().is_some_and(|&k| k < a) {
            deque.pop_front();
        }
        let inside = deque.front().map_or(f32::INFINITY, |&k| near[k]);
        let outside = row.far.min(pre[a]).min(suf[b + 1]);
        claimed.push(ratio_of(inside, outside));
    }
    let at = |col: usize| claimed[col - first];
    // The path's match unless another candidate is strictly better; nearer first, left first.
    let mut best = (j_star, at(j_star));
    for delta in 1..=c {
        let candidates = [j_star.checked_sub(delta), Some(j_star + delta)];
        for col in candidates.into_iter().flatten().filter(|&col| col <= last) {
            if at(col) > best.1 {
                best = (col, at(col));
            }
        }
    }
    (best.0, row.ratio(best.0, ro.radius))
}

/// The discounted readout of every `(row, path match)` in `targets` on `chat` (see the module
/// doc, [`Readout`] and [`Reading`]), in the order given. `discount` is `g`
/// in `(0, 1)`; rows and columns must be in the matrix (checked by the caller).
pub(super) fn discounted_readouts(
    chat: &Matrix,
    graph: &GraphParams,
    discount: f64,
    readout: Readout,
    targets: &[(usize, usize)],
) -> Vec<Reading> {
    let q = chat.rows();
    let mut wanted: Vec<Vec<(usize, usize)>> = vec![Vec::new(); q];
    for (t, &(i, j)) in targets.iter().enumerate() {
        wanted[i].push((t, j));
    }
    let scored: Vec<bool> = wanted.iter().map(|w| !w.is_empty()).collect();
    let rows = sweep(chat, graph, discount, &scored, |i, view| {
        wanted[i]
            .iter()
            .map(|&(t, j)| (t, read(view, readout, j, chat.row(i), graph.hidden_cost)))
            .collect::<Vec<_>>()
    });
    let mut result: Vec<Reading> = targets
        .iter()
        .map(|&(_, j)| Reading {
            at: j,
            confidence: 0.0,
            off_map: false,
            hidden_ratio: f64::INFINITY,
        })
        .collect();
    for (t, r) in rows.into_iter().flat_map(|(_, r)| r) {
        result[t] = r;
    }
    result
}

#[cfg(test)]
pub(super) mod plain;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::match_cost;
    use proptest::prelude::*;

    /// [`pick`] as first written: every candidate's band scanned anew, `O(claim · span)`.
    fn pick_direct(row: &Near<'_>, ro: Readout, j_star: usize, d: usize) -> (usize, f64) {
        let mut best = (j_star, row.ratio(j_star, ro.claim));
        for delta in 1..=ro.claim {
            let candidates = [j_star.checked_sub(delta), Some(j_star + delta)];
            for c in candidates.into_iter().flatten().filter(|&c| c < d) {
                let pinned = row.ratio(c, ro.claim);
                if pinned > best.1 {
                    best = (c, pinned);
                }
            }
        }
        (best.0, row.ratio(best.0, ro.radius))
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]
        /// The linear readout names the same frame with the same confidence, bit for bit, as
        /// scanning every candidate's band; values on a coarse grid (ties), some `+inf`.
        #[test]
        fn the_linear_claim_readout_is_the_direct_one(
            d in 1usize..60, j in 0usize..60, claim in 0usize..8, radius in 0usize..6,
            values in proptest::collection::vec(0u8..12, 120), far in 0u8..13,
        ) {
            let j_star = j % d;
            let span = claim + claim.max(radius);
            let lo = j_star.saturating_sub(span);
            let hi = (j_star + span).min(d - 1);
            let value = |v: u8| if v == 11 { f32::INFINITY } else { 1.0 + f32::from(v) / 4.0 };
            let near: Vec<f32> = values[..=hi - lo].iter().map(|&v| value(v)).collect();
            let row = Near { lo, near: &near, far: value(far) };
            let ro = Readout { radius, claim };
            let (fast, direct) = (pick(&row, ro, j_star), pick_direct(&row, ro, j_star, d));
            prop_assert_eq!(fast.0, direct.0);
            prop_assert_eq!(fast.1.to_bits(), direct.1.to_bits());
        }
    }

    /// Every route from row 0 to the last row by brute force, each node cost weighted by
    /// `g^|t-i|`; the ratio for row `i`, prediction `js`.
    fn brute_force(
        chat: &Matrix,
        gp: &GraphParams,
        g: f64,
        r: usize,
        i: usize,
        js: usize,
    ) -> crate::confidence::tests::Brute {
        let (q, d) = (chat.rows(), chat.cols());
        // Per row: a run [a, b] of one kind (matching or hidden), entered within the fan-out.
        let mut routes: Vec<Vec<(usize, usize, bool)>> = vec![Vec::new()];
        for t in 0..q {
            let mut next = Vec::new();
            for trace in &routes {
                let (lo, hi) = match trace.last() {
                    None => (0, d - 1),
                    Some(&(_, b, _)) => (b, (b + gp.fan_out).min(d - 1)),
                };
                for hidden in [false, true] {
                    for a in lo..=hi {
                        let max_b = if gp.horizontal { d - 1 } else { a };
                        for b in a..=max_b {
                            if !hidden && (a..=b).any(|j| match_cost(chat.get(t, j)).is_infinite())
                            {
                                continue;
                            }
                            let mut tr = trace.clone();
                            tr.push((a, b, hidden));
                            next.push(tr);
                        }
                    }
                }
            }
            routes = next;
        }
        let costs = routes.into_iter().map(|trace| {
            let cost: f64 = trace
                .iter()
                .enumerate()
                .map(|(t, &(a, b, hidden))| {
                    let c = if hidden {
                        gp.hidden_cost
                    } else {
                        (a..=b).map(|j| match_cost(chat.get(t, j))).sum()
                    };
                    c * g.powi((t as i32 - i as i32).abs())
                })
                .sum();
            (cost, trace[i])
        });
        crate::confidence::tests::ratio_of_routes(costs, js, r)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        #[test]
        fn discounted_ratio_matches_brute_force(
            q in 1usize..5, d in 1usize..5, seed in prop::collection::vec(-0.3f32..2.5, 20),
            k in 0usize..3, horizontal: bool, w in 0.3f64..2.5, g in 0.3f64..1.0, r in 0usize..2,
        ) {
            let chat = Matrix::from_vec(q, d, seed[..q * d].to_vec()).unwrap();
            let gp = GraphParams { fan_out: k, horizontal, hidden_cost: w };
            let targets: Vec<(usize, usize)> =
                (0..q).flat_map(|i| (0..d).map(move |j| (i, j))).collect();
            // Brute force for every row and column, at radius r and at radius 1.
            let at_r: Vec<Vec<_>> = (0..q)
                .map(|i| (0..d).map(|c| brute_force(&chat, &gp, g, r, i, c)).collect())
                .collect();
            let at_1: Vec<Vec<f64>> = (0..q)
                .map(|i| (0..d).map(|c| brute_force(&chat, &gp, g, 1, i, c).ratio).collect())
                .collect();
            let close = |a: f64, b: f64| (a - b).abs() <= 1e-5 * b.abs().max(1.0);
            // The ratio at the path's match (claim 0) and the off-the-map test there ...
            let ro = Readout { radius: r, claim: 0 };
            let fast = discounted_readouts(&chat, &gp, g, ro, &targets);
            for (&(i, js), f) in targets.iter().zip(&fast) {
                let slow = at_r[i][js];
                prop_assert_eq!(f.at, js);
                prop_assert!(close(f.confidence, slow.ratio), "row {i} col {js}: {} vs {}", f.confidence, slow.ratio);
                if let Some(off) = slow.off_map(1e-5, &chat, (i, js, r), w) {
                    prop_assert_eq!(f.off_map, off, "row {} col {}: {:?}", i, js, slow);
                }
            }
            // ... and the frame a claim of ±1 pins: the best-supported ±1 neighbourhood
            // within one frame of the match (up to rounding), scored at radius r.
            let ro = Readout { radius: r, claim: 1 };
            let pinned = discounted_readouts(&chat, &gp, g, ro, &targets);
            for (&(i, js), f) in targets.iter().zip(&pinned) {
                let at = f.at;
                prop_assert!(at.abs_diff(js) <= 1 && at < d, "row {i}: {at} from {js}");
                let best = (js.saturating_sub(1)..=(js + 1).min(d - 1))
                    .map(|c| at_1[i][c])
                    .fold(f64::NEG_INFINITY, f64::max);
                prop_assert!(at_1[i][at] >= best - 1e-5 * best.abs().max(1.0),
                    "row {i} col {js}: pinned {at} ({}) but the best is {best}", at_1[i][at]);
                let slow = at_r[i][at];
                prop_assert!(close(f.confidence, slow.ratio), "row {i} col {at}: {} vs {}", f.confidence, slow.ratio);
                if let Some(off) = slow.off_map(1e-5, &chat, (i, at, r), w) {
                    prop_assert_eq!(f.off_map, off, "row {} col {}: {:?}", i, at, slow);
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// The lanes (chunk borders, fix-ups, padding, windows longer than a chunk) and the
        /// meeting in the middle against the plain `f64` passes, on matrices too large to
        /// enumerate.
        #[test]
        fn the_sweep_matches_the_plain_passes(
            q in 1usize..24, d in 1usize..90, k in 0usize..12, horizontal: bool,
            w in 0.3f64..2.5, g in 0.3f64..0.95, r in 0usize..3, seed: u64,
        ) {
            let mut state = seed | 1;
            let chat = plain::noise_matrix(q, d, &mut state);
            let gp = GraphParams { fan_out: k, horizontal, hidden_cost: w };
            let targets: Vec<(usize, usize)> =
                (0..q).flat_map(|i| [(i, (i * 7) % d), (i, (i * 13 + 5) % d)]).collect();
            let ro = Readout { radius: r, claim: 0 };
            let fast = discounted_readouts(&chat, &gp, g, ro, &targets);
            let plain = plain::discounted_ratios(&chat, &gp, g, r, &targets);
            for ((&(i, j), r), p) in targets.iter().zip(&fast).zip(&plain) {
                let f = r.confidence;
                prop_assert!((f - p).abs() <= 1e-5 * p.abs().max(1.0),
                    "row {i} col {j}: {f} vs {p}");
            }
        }
    }
}
