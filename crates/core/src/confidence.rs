//! Confidence of a route hypothesis, per query row: the *local min-marginal ratio*.
//!
//! `ĉ` of the matched node is a poor confidence (spec §7: tunnel frames, whose tiny column means
//! inflate `ĉ`, come out most "confident"), and a global min-marginal (how much more the best
//! complete route that puts query `i` elsewhere costs) mostly measures how long the route has
//! been coherent, not whether the alignment *at row `i`* is right. SeqSLAM's answer is a local
//! ratio: the best sequence score near query `i` against the best one elsewhere. This module
//! applies the same idea to the flow graph itself:
//!
//! For query row `i` matched at reference `j*`, take the rows `i-L ..= i+L` (clamped to the
//! query) and the same graph restricted to them, with a free start in the first row and a free
//! end in the last (every node of the first window row is reachable from a virtual source at
//! cost 0 plus its own cost; every node of the last row reaches the sink at cost 0). With
//! `m(node)` = the cheapest window path through `node` (a forward plus a backward pass):
//!
//! * `inside`  = min `m(x_ij)` over `|j - j*| <= r` — the best local route that agrees with us;
//! * `outside` = min over `m(x_ij)` with `|j - j*| > r` and over every `m(h_ij)` — the best local
//!   route that puts query `i` somewhere else on the map, or off the map;
//! * confidence = `outside / inside`. Above 1 means the local evidence prefers `j*`; a route
//!   that is right only because of distant context (a tunnel, a station where the train stands)
//!   gets a ratio near 1.
//!
//! Both costs are sums of positive node costs, so the ratio is finite and positive whenever
//! `inside` is finite. Defaults: `L = 5` (an 11-frame window, about SeqSLAM's `ds = 10`) and
//! `r = 2` (alternatives within two frames are the same place at the resolution a route is
//! matched). On the Nordland dev split these give recall 0.45-0.57 at 99 % precision for
//! `L` in 3..=8 and `r` in 1..=4, where `ĉ` gives about 0: the choice is not knife-edge.
//!
//! Cost: `2L+1` row updates of `D` columns per matched query row, rows in parallel (rayon); the
//! forward updates use the solver's row kernel.
//!
//! **The default offline is the discounted ratio** (`discounted.rs`, [`DEFAULT_DISCOUNT`]): the
//! same inside/outside ratio on the whole query, each row's node costs weighted `g^|t-i|` by
//! its distance to the scored row instead of the box window's 1 inside / 0 outside. It is one
//! forward and one backward pass for all rows (`O(Q·D)` in total instead of `(2L+1)·Q·D`), and it
//! has no window edge: evidence fades with distance instead of stopping at `L`. Measured effect
//! and held-out results: ARCHITECTURE.md ("Confidence"). Trips score with the discounted ratio
//! in its causal form (`trip/confidence.rs`); the box window ([`window_readout`]) stays
//! selectable, [`ConfidenceParams::window`].

use rayon::prelude::*;

mod discounted;
mod stretch;
mod sweep;

pub use stretch::{
    chance_contrast, chance_marks, chance_stretches, row_contrast, weak_stretches, RowSpread,
    OUTLIER_CONTRAST, SAMPLE, STRONG,
};

use crate::solver::{forward_values_row, match_cost, Hypothesis, RowScratch};
use crate::window::leading_min_in_place;
use crate::{Error, Matrix, Result};

/// Parameters of the local min-marginal ratio.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConfidenceParams {
    /// `L`: rows on each side of the scored row that form its window.
    pub half_window: usize,
    /// `r`: alternatives within `r` reference frames of the match count as the same place.
    pub radius: usize,
    /// `g` in `(0, 1)`: score with the discounted min-marginal ratio instead of the box window
    /// (rows weighted `g^|t-i|` over the whole route, `O(Q·D)` in total; `discounted.rs`).
    /// `None`: the box window of `half_window` (offline only: a trip always scores with the
    /// discounted ratio, `g = 1 - 1/(half_window + 1)` when this is `None`,
    /// [`crate::trip::TripParams::discount`]).
    pub discount: Option<f64>,
}

/// The default discount `g = 1 - 1/(L+1)` for `L = 5`: a row `L` frames away still weighs
/// `g^L = 0.40`, as the box window of half-width `L` gave its edge rows full weight and
/// nothing beyond (not tuned: `g` in 0.75..=0.9 measured in ARCHITECTURE.md).
pub const DEFAULT_DISCOUNT: f64 = 5.0 / 6.0;

impl Default for ConfidenceParams {
    /// The discounted ratio with `g` = [`DEFAULT_DISCOUNT`], `r = 2`: the default offline and,
    /// in its causal form on the frames seen so far, for trips (`trip/confidence.rs`).
    fn default() -> Self {
        ConfidenceParams {
            half_window: 5,
            radius: 2,
            discount: Some(DEFAULT_DISCOUNT),
        }
    }
}

impl ConfidenceParams {
    /// The rows on each side of a scored row whose evidence its confidence rests on: the box
    /// window's half-width `L`, or for the discounted ratio the mean distance of its row
    /// weights `g^k`, `g / (1 - g)` (5 for the default `g = 5/6`, the `L` it was derived from).
    pub fn evidence_span(&self) -> usize {
        match self.discount {
            Some(g) if g > 0.0 && g < 1.0 => (g / (1.0 - g)).round() as usize,
            _ => self.half_window,
        }
    }

    /// Matched rows in a stretch the stretch rule judges (`stretch.rs`): the evidence span on
    /// both sides, `2 · `[`Self::evidence_span`] (10 by default), offline and in trips.
    pub fn stretch_len(&self) -> usize {
        2 * self.evidence_span()
    }

    /// The box window of half-width 5, `r = 2`: the offline default of earlier versions
    /// (`eval --confidence window`).
    pub fn window() -> Self {
        ConfidenceParams {
            discount: None,
            ..ConfidenceParams::default()
        }
    }
}

/// The graph a hypothesis was found on: what the confidence needs to rebuild its windows.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GraphParams {
    /// Fan-out `K`.
    pub fan_out: usize,
    /// Horizontal edges on or off.
    pub horizontal: bool,
    /// The hidden cost `W` that was used.
    pub hidden_cost: f64,
}

/// One scored row of a hypothesis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RowConfidence {
    /// Query row `i`.
    pub query: usize,
    /// The reference the row is predicted at: its match with the highest `ĉ`.
    pub reference: usize,
    /// `outside / inside` (see the module doc); 0 when no local route agrees with the match.
    pub confidence: f64,
    /// The row's own min-marginals put it off the map rather than at the place
    /// ([`off_the_map`]: a local route hidden at this row costs little more than the best one
    /// through a match within `r` of `reference`, measured against what hiding that route at
    /// the row would cost), and a localization leaves it without a prediction
    /// (ARCHITECTURE.md, "Off the map").
    pub off_map: bool,
    /// The cheapest local route hidden at the row over the cheapest through the band (`+inf`
    /// when none passes the band): how much the row's own evidence holds it on the map, an
    /// input of the calibrated `p_correct` ([`crate::calibration`]).
    pub hidden_ratio: f64,
}

/// Scores every matched row of `hypothesis` on the normalised similarity matrix `chat`.
/// Hidden rows get no entry.
pub fn score_hypothesis(
    chat: &Matrix,
    graph: &GraphParams,
    hypothesis: &Hypothesis,
    params: &ConfidenceParams,
) -> Result<Vec<RowConfidence>> {
    let mut scored = score_hypotheses(chat, graph, std::slice::from_ref(hypothesis), params, 0)?;
    Ok(scored.pop().unwrap_or_default())
}

/// [`score_hypothesis`] for several hypotheses of one matrix at once: the discounted ratio
/// runs its two passes once for all of them (the passes do not depend on the hypothesis,
/// only the rows read out do).
///
/// `claim` (`c`, discounted ratio only): the frames a prediction claims on each side of the
/// frame it names. With `c > 0` a row is predicted at the frame within `c` of the path's
/// match whose `±c` neighbourhood the evidence supports best (the largest ratio at radius
/// `c`), and scored with the ratio at radius `r` there: a sub-frame readout of the path
/// (ARCHITECTURE.md, "Confidence"). `c = 0` names the path's match itself.
pub fn score_hypotheses(
    chat: &Matrix,
    graph: &GraphParams,
    hypotheses: &[Hypothesis],
    params: &ConfidenceParams,
    claim: usize,
) -> Result<Vec<Vec<RowConfidence>>> {
    let routes: Vec<Vec<(usize, usize)>> = hypotheses
        .iter()
        .map(|h| h.rows.iter().filter_map(predicted_at).collect())
        .collect();
    let mut scored = read_hypotheses(chat, graph, &routes, params, claim)?;
    // A stretch of a route's matches no more distinct than chance is off the map too
    // (`stretch.rs`): rows hidden by the route itself are not part of any stretch.
    let len = params.stretch_len();
    let bar = chance_contrast(graph.fan_out.saturating_add(1));
    let marks = chance_stretches(chat, &routes, len, bar);
    for (rows, weak) in scored.iter_mut().zip(marks) {
        for (row, weak) in rows.iter_mut().zip(weak) {
            row.off_map |= weak;
        }
    }
    Ok(scored)
}

/// The confidence readout of each hypothesis's matched rows (`per_hypothesis`: `(row,
/// reference)` of each, in row order), after checking that they lie in `chat`.
fn read_hypotheses(
    chat: &Matrix,
    graph: &GraphParams,
    per_hypothesis: &[Vec<(usize, usize)>],
    params: &ConfidenceParams,
    claim: usize,
) -> Result<Vec<Vec<RowConfidence>>> {
    crate::solver::check_hidden_cost(graph.hidden_cost)?;
    if let Some(&(i, j)) = per_hypothesis
        .iter()
        .flatten()
        .find(|(i, j)| *i >= chat.rows() || *j >= chat.cols())
    {
        return Err(Error::Shape(format!(
            "hypothesis matches query {i} to reference {j}, outside the {}x{} matrix",
            chat.rows(),
            chat.cols()
        )));
    }
    let rows = |targets: &[(usize, usize)], read: &[WindowReading]| -> Vec<RowConfidence> {
        targets
            .iter()
            .zip(read)
            .map(|(&(i, j), r)| RowConfidence {
                query: i,
                reference: j,
                confidence: r.confidence,
                off_map: r.off_map,
                hidden_ratio: r.hidden_ratio,
            })
            .collect()
    };
    if let Some(g) = params.discount {
        if g.is_nan() || g <= 0.0 || g >= 1.0 {
            return Err(Error::param(
                "discount",
                format!("must be within (0, 1), got {g}"),
            ));
        }
        let all: Vec<(usize, usize)> = per_hypothesis.iter().flatten().copied().collect();
        let readout = discounted::Readout {
            radius: params.radius,
            claim,
        };
        let read = discounted::discounted_readouts(chat, graph, g, readout, &all);
        let mut read = read.into_iter();
        return Ok(per_hypothesis
            .iter()
            .map(|targets| {
                targets
                    .iter()
                    .zip(read.by_ref())
                    .map(|(&(i, _), r)| RowConfidence {
                        query: i,
                        reference: r.at,
                        confidence: r.confidence,
                        off_map: r.off_map,
                        hidden_ratio: r.hidden_ratio,
                    })
                    .collect()
            })
            .collect());
    }
    Ok(per_hypothesis
        .iter()
        .map(|targets| {
            let read: Vec<WindowReading> = targets
                .par_iter()
                .map(|&(i, j)| local_readout(chat, graph, params, i, j))
                .collect();
            rows(targets, &read)
        })
        .collect())
}

/// The `(row, reference)` a row of a hypothesis predicts: its match with the highest `ĉ`.
fn predicted_at(row: &crate::solver::RowAssignment) -> Option<(usize, usize)> {
    let best = row
        .matches
        .iter()
        .max_by(|a, b| a.similarity.total_cmp(&b.similarity))?;
    Some((row.query, best.reference))
}

fn local_readout(
    chat: &Matrix,
    graph: &GraphParams,
    params: &ConfidenceParams,
    i: usize,
    j_star: usize,
) -> WindowReading {
    let first = i.saturating_sub(params.half_window);
    let last = (i + params.half_window).min(chat.rows() - 1);
    let rows: Vec<&[f32]> = (first..=last).map(|t| chat.row(t)).collect();
    window_readout(&rows, i - first, graph, params.radius, j_star)
}

/// What the box window says of one row: the ratio and whether the best window route hidden
/// at the row beats every one through the band (see [`RowConfidence`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WindowReading {
    /// `outside / inside` ([`window_readout`]).
    pub confidence: f64,
    /// The off-the-map test ([`off_the_map`], [`RowConfidence::off_map`]).
    pub off_map: bool,
    /// `hidden / inside` ([`RowConfidence::hidden_ratio`]).
    pub hidden_ratio: f64,
}

/// The local min-marginal ratio of matching `rows[scored]` at `j_star`, on the graph restricted
/// to `rows` (consecutive `ĉ` rows, all of the same length, free start and free end), and the
/// off-the-map test of the same window ([`WindowReading`]).
///
/// The forward rows use the solver's row kernel ([`crate::solver`], same operations as the
/// shortest path); the backward rows are plain right-to-left passes over precomputed costs.
pub fn window_readout(
    rows: &[&[f32]],
    scored: usize,
    graph: &GraphParams,
    radius: usize,
    j_star: usize,
) -> WindowReading {
    let d = rows[scored].len();
    let (i, last) = (scored, rows.len() - 1);
    let w = graph.hidden_cost;
    let k = graph.fan_out;

    // Forward pass, free start at the first row: fx/fh = cheapest window path ending at the node.
    let mut fx = vec![0.0f64; d];
    let mut fh = vec![0.0f64; d];
    let mut m_prev = vec![0.0f64; d];
    let mut m_cur = vec![0.0f64; d];
    let mut scratch = RowScratch::default();
    for (t, row) in rows[..=i].iter().enumerate() {
        let prev = (t > 0).then_some(&m_prev[..]);
        let out = (&mut fx[..], &mut fh[..], &mut m_cur[..]);
        forward_values_row(row, prev, k, graph.horizontal, w, out, &mut scratch);
        std::mem::swap(&mut m_prev, &mut m_cur);
    }

    // Backward pass, free end at `last`: bx/bh = cheapest continuation after the node.
    let mut bx = vec![0.0f64; d];
    let mut bh = vec![0.0f64; d];
    let mut next = vec![0.0f64; d];
    let mut cost = vec![0.0f64; d];
    for t in (i..last).rev() {
        for (c, &v) in cost.iter_mut().zip(rows[t + 1]) {
            *c = match_cost(v);
        }
        for (((n, &c), &x), &h) in next.iter_mut().zip(&cost).zip(&bx).zip(&bh) {
            *n = (c + x).min(w + h);
        }
        leading_min_in_place(&mut next, k, &mut m_cur);
        if graph.horizontal {
            for (c, &v) in cost.iter_mut().zip(rows[t]) {
                *c = match_cost(v);
            }
            // bx[j] = min(succ[j], c[j+1] + bx[j+1]), bh[j] = min(succ[j], bh[j+1]).
            let (mut right_x, mut right_h) = (f64::INFINITY, f64::INFINITY);
            let cells = next.iter().zip(&cost).zip(bx.iter_mut().zip(bh.iter_mut()));
            for ((&s, &c), (x, h)) in cells.rev() {
                *x = s.min(right_x);
                *h = s.min(right_h);
                right_x = c + *x;
                right_h = *h;
            }
        } else {
            bx.copy_from_slice(&next);
            bh.copy_from_slice(&next);
        }
    }

    let band = band_costs((&fx, &fh), (&bx, &bh), j_star, radius);
    WindowReading {
        confidence: band.ratio(),
        hidden_ratio: if band.inside.is_finite() && band.inside > 0.0 {
            band.hidden / band.inside
        } else {
            f64::INFINITY
        },
        off_map: off_the_map(
            band.hidden,
            band.inside,
            best_node_cost(rows[scored], j_star, radius),
            w,
        ),
    }
}

/// The costs one row is read from: the cheapest route through the band (`inside`), through
/// another column or a hidden node (`outside`), and hidden at the row (`hidden`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct BandCosts {
    pub inside: f64,
    pub outside: f64,
    pub hidden: f64,
}

impl BandCosts {
    /// `outside / inside`, 0 when no route passes inside the band.
    pub(crate) fn ratio(&self) -> f64 {
        if self.inside.is_finite() {
            self.outside / self.inside
        } else {
            0.0
        }
    }
}

/// The band costs of one row from its forward values `fx`, `fh` (cheapest route ending at
/// each matching / hidden node) and backward values `bx`, `bh` (cheapest continuation after
/// it), with the columns within `radius` of `j_star` as the band. The box window and the
/// trips' causal discounted ratio (`trip/confidence.rs`) both read their rows with it.
pub(crate) fn band_costs(
    (fx, fh): (&[f64], &[f64]),
    (bx, bh): (&[f64], &[f64]),
    j_star: usize,
    radius: usize,
) -> BandCosts {
    let d = fx.len();
    let lo = j_star.saturating_sub(radius);
    let hi = (j_star + radius).min(d - 1);
    let (mut inside, mut outside, mut hidden) = (f64::INFINITY, f64::INFINITY, f64::INFINITY);
    for j in 0..d {
        let through_x = fx[j] + bx[j];
        if (lo..=hi).contains(&j) {
            inside = inside.min(through_x);
        } else {
            outside = outside.min(through_x);
        }
        hidden = hidden.min(fh[j] + bh[j]);
    }
    BandCosts {
        inside,
        outside: outside.min(hidden),
        hidden,
    }
}

/// The cost `1/ĉ` of the best matching node of `row` within `radius` of `centre` (`+inf` when
/// none is usable): the row's own evidence for the place, in the graph's units.
pub fn best_node_cost(row: &[f32], centre: usize, radius: usize) -> f64 {
    let lo = centre.saturating_sub(radius);
    let hi = (centre + radius).min(row.len().saturating_sub(1));
    row.get(lo..=hi)
        .unwrap_or_default()
        .iter()
        .map(|&v| match_cost(v))
        .fold(f64::INFINITY, f64::min)
}

/// The share of a row's stake ([`off_the_map`]) within which a route hidden at the row puts
/// the row off the map. 0 would be the plain test `hidden < inside`, 1 would hide every row
/// whose best route gains anything by being hidden there. Chosen from the measured range
/// (ARCHITECTURE.md, "Off the map"): at 0.25 Nordland dev (HOG and CNN) moves by at most 0.001
/// AP and the six Gardens Point pairings not at all, while 46 of the 50 Nordland detour rows
/// are hidden (32 with 0); 0.5 hides all 50 but costs weak similarities (the co-occurrence
/// scores in the graph, the pooled CNN) 0.01-0.02 AP.
pub const OFF_MAP_SHARE: f64 = 0.25;

/// The off-the-map test of a scored row (ARCHITECTURE.md, "Off the map"). `hidden` is the
/// cheapest route hidden at the row, `inside` the cheapest through the band, `node` the cost
/// of the band's best node in the row ([`best_node_cost`]) and `w` the hidden cost. Taking the
/// band's route and hiding it at the row costs at most `inside - node + w`: the row's *stake*
/// is `w - node`. The row is off the map when a route hidden there costs less than a quarter
/// ([`OFF_MAP_SHARE`]) of that stake more than `inside`: hiding the row frees the route to
/// take another course that recovers most of what hiding costs, so the match is held by the
/// route's commitment rather than by the image. With no usable node in the band this is
/// `hidden < inside`.
pub fn off_the_map(hidden: f64, inside: f64, node: f64, w: f64) -> bool {
    if inside.is_finite() && node.is_finite() {
        hidden < inside + OFF_MAP_SHARE * (w - node)
    } else {
        hidden < inside
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::{Match, RowAssignment};
    use proptest::prelude::*;

    /// Every path through the window graph, by brute force: (node per row as (col, hidden)),
    /// costs summed over nodes. Used to check `local_ratio` on tiny matrices.
    fn brute_force_ratio(
        chat: &Matrix,
        g: &GraphParams,
        p: &ConfidenceParams,
        i: usize,
        js: usize,
    ) -> Brute {
        let first = i.saturating_sub(p.half_window);
        let last = (i + p.half_window).min(chat.rows() - 1);
        let d = chat.cols();
        // States are (col, hidden). Within a row a path is a run of horizontal moves of one kind.
        // Enumerate, per row, the segment [entry..=exit] and the kind.
        #[allow(clippy::too_many_arguments, clippy::type_complexity)]
        fn rec(
            chat: &Matrix,
            g: &GraphParams,
            t: usize,
            last: usize,
            entry_min: usize,
            entry_max: usize,
            cost: f64,
            trace: &mut Vec<(usize, usize, bool)>,
            out: &mut Vec<(f64, Vec<(usize, usize, bool)>)>,
        ) {
            let d = chat.cols();
            for hidden in [false, true] {
                for a in entry_min..=entry_max.min(d - 1) {
                    let max_b = if g.horizontal { d - 1 } else { a };
                    for b in a..=max_b {
                        let seg: f64 = if hidden {
                            g.hidden_cost
                        } else {
                            (a..=b).map(|j| match_cost(chat.get(t, j))).sum()
                        };
                        if !seg.is_finite() {
                            continue;
                        }
                        trace.push((a, b, hidden));
                        if t == last {
                            out.push((cost + seg, trace.clone()));
                        } else {
                            rec(
                                chat,
                                g,
                                t + 1,
                                last,
                                b,
                                b + g.fan_out,
                                cost + seg,
                                trace,
                                out,
                            );
                        }
                        trace.pop();
                    }
                }
            }
        }
        let mut all = Vec::new();
        rec(
            chat,
            g,
            first,
            last,
            0,
            d - 1,
            0.0,
            &mut Vec::new(),
            &mut all,
        );
        ratio_of_routes(
            all.iter().map(|(cost, trace)| (*cost, trace[i - first])),
            js,
            p.radius,
        )
    }

    /// What brute-forced routes say of one row: the ratio, the cheapest route hidden at the
    /// row and the cheapest through the band.
    #[derive(Clone, Copy, Debug)]
    pub(super) struct Brute {
        pub ratio: f64,
        pub hidden: f64,
        pub inside: f64,
    }

    impl Brute {
        /// The off-the-map test for row `i` at column `at` (radius `r`, hidden cost `w`):
        /// the cheapest route hidden at the row costs less than `inside` plus
        /// [`OFF_MAP_SHARE`] of the row's stake (`w` minus the cost of the band's best node,
        /// brute-forced here from `chat`). `None` when `hidden` is within `tol` (relative) of
        /// that bar: the fast passes' rounding may decide it either way.
        pub fn off_map(
            &self,
            tol: f64,
            chat: &Matrix,
            (i, at, r): (usize, usize, usize),
            w: f64,
        ) -> Option<bool> {
            let node = (0..chat.cols())
                .filter(|j| j.abs_diff(at) <= r)
                .map(|j| match_cost(chat.get(i, j)))
                .fold(f64::INFINITY, f64::min);
            let bar = if self.inside.is_finite() && node.is_finite() {
                self.inside + OFF_MAP_SHARE * (w - node)
            } else {
                self.inside
            };
            let scale = self.hidden.abs().max(bar.abs()).max(1.0);
            let tie = (self.hidden - bar).abs() <= tol * scale
                || (self.hidden.is_infinite() && bar.is_infinite());
            (!tie).then_some(self.hidden < bar)
        }
    }

    /// The min-marginal ratio from brute-forced routes, given as each route's cost and its run
    /// `(first column, last column, hidden)` in the scored row: the cheapest route that leaves
    /// the window `js ± r` (or is hidden there) over the cheapest that enters it; 0 when none
    /// enters it. The brute forces of both confidences (box and discounted) share it.
    pub(super) fn ratio_of_routes(
        routes: impl IntoIterator<Item = (f64, (usize, usize, bool))>,
        js: usize,
        r: usize,
    ) -> Brute {
        let (lo, hi) = (js.saturating_sub(r), js + r);
        let (mut best_in, mut best_out, mut hidden_at) =
            (f64::INFINITY, f64::INFINITY, f64::INFINITY);
        for (cost, (a, b, hidden)) in routes {
            if hidden {
                hidden_at = hidden_at.min(cost);
                continue;
            }
            if (a..=b).any(|j| (lo..=hi).contains(&j)) {
                best_in = best_in.min(cost);
            }
            if (a..=b).any(|j| !(lo..=hi).contains(&j)) {
                best_out = best_out.min(cost);
            }
        }
        let best_out = best_out.min(hidden_at);
        Brute {
            ratio: if best_in.is_finite() {
                best_out / best_in
            } else {
                0.0
            },
            hidden: hidden_at,
            inside: best_in,
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn local_ratio_matches_brute_force(
            q in 1usize..5, d in 1usize..6, seed in prop::collection::vec(-0.3f32..2.5, 30),
            k in 0usize..3, horizontal: bool, w in 0.3f64..2.5, hw in 0usize..3, r in 0usize..2,
        ) {
            let chat = Matrix::from_vec(q, d, seed[..q * d].to_vec()).unwrap();
            let g = GraphParams { fan_out: k, horizontal, hidden_cost: w };
            let p = ConfidenceParams { half_window: hw, radius: r, discount: None };
            for i in 0..q {
                for js in 0..d {
                    let fast = local_readout(&chat, &g, &p, i, js);
                    let slow = brute_force_ratio(&chat, &g, &p, i, js);
                    let (f, b) = (fast.confidence, slow.ratio);
                    prop_assert!((f - b).abs() <= 1e-9 * b.abs().max(1.0), "row {i} col {js}: {f} vs {b}");
                    if let Some(off) = slow.off_map(1e-9, &chat, (i, js, r), w) {
                        prop_assert_eq!(fast.off_map, off, "row {} col {}: {:?}", i, js, slow);
                    }
                }
            }
        }
    }

    fn hypothesis(rows: &[Option<(usize, f32)>]) -> Hypothesis {
        Hypothesis {
            rank: 1,
            cost: 0.0,
            rows: rows
                .iter()
                .enumerate()
                .map(|(i, m)| RowAssignment {
                    query: i,
                    matches: m
                        .iter()
                        .map(|&(reference, similarity)| Match {
                            reference,
                            similarity,
                        })
                        .collect(),
                })
                .collect(),
        }
    }

    #[test]
    fn a_distinct_diagonal_is_more_confident_than_an_ambiguous_one() {
        // 8 queries x 12 references; rows 0..4 have a sharp diagonal, rows 4..8 a diagonal whose
        // similarity is equalled by a parallel diagonal 6 columns away.
        let mut chat = Matrix::from_vec(8, 12, vec![1.0; 96]).unwrap();
        for i in 0..8 {
            chat.set(i, i, 2.0);
            if i >= 4 && i + 4 < 12 {
                chat.set(i, i + 4, 2.0);
            }
        }
        let g = GraphParams {
            fan_out: 2,
            horizontal: true,
            hidden_cost: 1.5,
        };
        let p = ConfidenceParams {
            half_window: 1,
            radius: 1,
            discount: None,
        };
        let h = hypothesis(&(0..8).map(|i| Some((i, 2.0))).collect::<Vec<_>>());
        let conf = score_hypothesis(&chat, &g, &h, &p).unwrap();
        assert_eq!(conf.len(), 8);
        assert!(conf[1].confidence > 1.2, "{conf:?}");
        assert!(conf[6].confidence < conf[1].confidence, "{conf:?}");
        assert!((conf[6].confidence - 1.0).abs() < 1e-9, "{conf:?}");
    }

    #[test]
    fn a_row_is_off_the_map_when_hiding_it_wins_back_most_of_its_stake() {
        // inside 10, the band's best node costs 0.8 (ĉ 1.25), W = 1.2: the stake is 0.4, and
        // hiding the band's route at the row costs at most 10.4.
        let (inside, node, w) = (10.0, 0.8, 1.2);
        let bar = inside + OFF_MAP_SHARE * (w - node);
        // A hidden route that beats the place outright, or costs less than the bar: off.
        assert!(off_the_map(9.9, inside, node, w));
        assert!(off_the_map(bar - 1e-9, inside, node, w));
        // At the bar or above (hiding frees the route too little): the image holds the match.
        assert!(!off_the_map(bar, inside, node, w));
        assert!(!off_the_map(10.4, inside, node, w));
        // A best node dearer than W (stake -0.1): hiding the band's route at the row costs at
        // most 9.9, below the bar (9.975), so such a row is always off the map.
        assert!(off_the_map(inside - 1.3 + w, inside, 1.3, w));
        // No usable node or no route through the band: the plain comparison.
        assert!(off_the_map(5.0, f64::INFINITY, f64::INFINITY, w));
        assert!(!off_the_map(f64::INFINITY, f64::INFINITY, f64::INFINITY, w));
        assert!(!off_the_map(10.1, inside, f64::INFINITY, w));
        // The band's best node is the cheapest within the radius; unusable entries cost +inf.
        let row = [2.0f32, 0.5, -1.0, 1.25, 4.0];
        assert_eq!(best_node_cost(&row, 2, 1), 0.8);
        assert_eq!(best_node_cost(&row, 0, 0), 0.5);
        assert_eq!(best_node_cost(&row, 4, 3), 0.25);
        assert_eq!(best_node_cost(&[-1.0, 0.0], 0, 1), f64::INFINITY);
    }

    #[test]
    fn hidden_rows_get_no_confidence_and_the_best_match_of_a_row_is_predicted() {
        let chat = Matrix::from_vec(
            3,
            4,
            vec![2.0, 1.0, 1.0, 1.0, 1.0, 1.5, 3.0, 1.0, 1.0, 1.0, 1.0, 2.0],
        )
        .unwrap();
        let mut h = hypothesis(&[Some((0, 2.0)), None, Some((3, 2.0))]);
        h.rows[1].matches = vec![
            Match {
                reference: 1,
                similarity: 1.5,
            },
            Match {
                reference: 2,
                similarity: 3.0,
            },
        ];
        let g = GraphParams {
            fan_out: 1,
            horizontal: true,
            hidden_cost: 1.2,
        };
        let at = |conf: &[RowConfidence]| {
            conf.iter()
                .map(|c| (c.query, c.reference))
                .collect::<Vec<_>>()
        };
        for params in [ConfidenceParams::default(), ConfidenceParams::window()] {
            let conf = score_hypothesis(&chat, &g, &h, &params).unwrap();
            assert_eq!(at(&conf), vec![(0, 0), (1, 2), (2, 3)], "{params:?}");
        }
        // A claim of ±1 names, within one frame of each match, the frame whose ±1
        // neighbourhood is best supported: on four columns the ends move inwards (their
        // neighbourhoods hold two columns, the inner ones three).
        let claimed =
            score_hypotheses(&chat, &g, &[h.clone()], &ConfidenceParams::default(), 1).unwrap();
        assert_eq!(at(&claimed[0]), vec![(0, 1), (1, 2), (2, 2)]);
        let none = score_hypothesis(
            &chat,
            &g,
            &hypothesis(&[None, None, None]),
            &ConfidenceParams::default(),
        )
        .unwrap();
        assert!(none.is_empty());
    }

    #[test]
    fn a_match_outside_the_matrix_is_an_error() {
        let chat = Matrix::from_vec(1, 2, vec![1.0, 1.0]).unwrap();
        let g = GraphParams {
            fan_out: 1,
            horizontal: true,
            hidden_cost: 1.2,
        };
        let err = score_hypothesis(
            &chat,
            &g,
            &hypothesis(&[Some((5, 1.0))]),
            &ConfidenceParams::default(),
        )
        .unwrap_err();
        assert!(err.to_string().contains("reference 5"), "{err}");
    }
}
