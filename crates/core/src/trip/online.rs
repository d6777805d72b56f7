//! Online localization for trips: the `F = 1` shortest path of the flow graph, extended one query
//! row at a time as frames arrive.
//!
//! The offline solver ([`crate::solver`]) sweeps the DAG row by row; the cost of the best path
//! ending at each node of row `i` depends only on row `i-1`. [`OnlineSolver`] keeps exactly that
//! state — two cost vectors of length `D` — so each new row costs `O(D)` whatever the trip's
//! length. Back-pointers are kept for the last `lag` rows only: the best path is re-traced over
//! that window after every batch (smoothing recent estimates as evidence arrives), and a row
//! that leaves the window is *committed* with the estimate it had then. Memory per trip is
//! `O(lag · D)`.
//!
//! Without relocalization the graph is the offline one, so the estimate reported for the latest
//! row equals what an offline solve of the rows so far gives for its last row.
//!
//! **Relocalization** (beyond the paper): the forward-only graph cannot return to an earlier
//! part of the route. With `relocalization = Some(R)`, every node of row `i` also has an edge
//! from the cheapest node of row `i-1` (anywhere on the map) that costs `R` plus the entered
//! node's own cost. A path therefore jumps only when the new place is cheaper than the old one
//! by more than `R` summed over the following frames — the vehicle has to look lost (its old
//! matches poor) for a while before it is found elsewhere.
//!
//! Code: the row step itself (the graph one row at a time, back-pointers, scratch) is in
//! `online/step.rs`; this file keeps the parameters, the lag window, commits, the trace and
//! the solver's stored form.

use std::collections::VecDeque;

use crate::confidence::GraphParams;
use crate::solver::{check_fan_out, check_hidden_cost};
use crate::{Error, Result};

use super::state::{corrupt, StateReader, StateWriter};

mod step;

use step::{step, Back, Costs, RowBack, StepScratch};

/// Parameters of an online solver.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OnlineParams {
    /// Fan-out `K`, horizontal edges and hidden cost `W` of the graph.
    pub graph: GraphParams,
    /// Rows whose back-pointers are kept; older rows are committed. At least 1.
    pub lag: usize,
    /// Cost `R` of re-entering the map anywhere; `None` keeps the paper's forward-only graph.
    pub relocalization: Option<f64>,
}

/// Largest accepted lag window.
pub const MAX_LAG: usize = 10_000;

impl OnlineParams {
    /// Checks every parameter's range.
    pub fn validate(&self) -> Result<()> {
        check_fan_out(self.graph.fan_out)?;
        check_hidden_cost(self.graph.hidden_cost)?;
        check_window(self.lag, self.relocalization)
    }
}

/// Checks the lag window (1 ..= [`MAX_LAG`]) and the relocalization cost (finite, >= 0).
pub(crate) fn check_window(lag: usize, relocalization: Option<f64>) -> Result<()> {
    if lag == 0 || lag > MAX_LAG {
        return Err(Error::param(
            "lag",
            format!("must be between 1 and {MAX_LAG}, got {lag}"),
        ));
    }
    if let Some(r) = relocalization {
        if !(r.is_finite() && r >= 0.0) {
            return Err(Error::param(
                "relocalization_cost",
                format!("must be a finite number >= 0, got {r}"),
            ));
        }
    }
    Ok(())
}

/// The estimate for one row on the current best path.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RowEstimate {
    /// Row (frame) index since the trip started.
    pub row: usize,
    /// The matched reference with the highest `ĉ` in that row, or `None` when hidden.
    pub reference: Option<usize>,
    /// The path entered this row by a relocalization jump.
    pub relocalized: bool,
}

/// Incremental `F = 1` solver over a fixed map of `D` reference columns.
///
/// Besides the cost rows of the latest row it can keep those of the row before its lag window
/// (the *window base*), advanced by the same row step as rows leave the window: a solver
/// restored from the base costs and the window's `ĉ` rows ([`OnlineSolver::base_image`] +
/// [`OnlineSolver::push_row`]) is bit-identical to this one, which is what lets a trip store
/// the base once in a while and only the rows in between ([`crate::trip`]).
#[derive(Clone)]
pub struct OnlineSolver {
    params: OnlineParams,
    d: usize,
    cur: Costs,
    /// The costs before the window's first row (`None` when not tracked: a state restored
    /// from a format that did not keep it).
    base: Option<Costs>,
    window: VecDeque<RowBack>,
    /// `ĉ` of the rows in the window (needed to pick a row's best match when several).
    window_chat: VecDeque<Vec<f32>>,
    scratch: StepScratch,
}

impl OnlineSolver {
    /// A solver for a map of `references` columns.
    pub fn new(references: usize, params: OnlineParams) -> Result<Self> {
        params.validate()?;
        if references == 0 {
            return Err(Error::Empty("the map has no reference images".into()));
        }
        if references > Back::MAX_COLUMN {
            return Err(Error::Shape(format!(
                "maps are limited to {} references",
                Back::MAX_COLUMN
            )));
        }
        Ok(OnlineSolver {
            params,
            d: references,
            cur: Costs::new(references),
            base: Some(Costs::new(references)),
            window: VecDeque::with_capacity(params.lag + 1),
            window_chat: VecDeque::with_capacity(params.lag + 1),
            scratch: StepScratch::new(references),
        })
    }

    /// Rows consumed so far.
    pub fn rows(&self) -> usize {
        self.cur.rows
    }

    /// Whether the window base's costs are kept (see the type's doc).
    pub fn tracks_base(&self) -> bool {
        self.base.is_some()
    }

    /// The parameters.
    pub fn params(&self) -> &OnlineParams {
        &self.params
    }

    /// The `ĉ` rows of the lag window, oldest first (row `rows() - len + k` at index `k`).
    pub fn window_rows(&self) -> &VecDeque<Vec<f32>> {
        &self.window_chat
    }

    /// Number of reference columns `D`.
    pub fn references(&self) -> usize {
        self.d
    }

    /// Approximate heap bytes held (vectors' capacities, window and window base included).
    pub fn heap_bytes(&self) -> usize {
        let window: usize = self
            .window
            .iter()
            .map(|b| (b.x.capacity() + b.h.capacity()) * 4)
            .sum::<usize>()
            + self
                .window_chat
                .iter()
                .map(|c| c.capacity() * 4)
                .sum::<usize>();
        let costs = |c: &Costs| (c.x.capacity() + c.h.capacity()) * 8;
        costs(&self.cur) + self.base.as_ref().map_or(0, costs) + self.scratch.heap_bytes() + window
    }

    /// Extends the path by one row of `ĉ` (length `D`, finite). Returns the row that left the
    /// lag window with its committed estimate, if one did.
    pub fn push_row(&mut self, chat_row: &[f32]) -> Result<Option<RowEstimate>> {
        self.check_row(chat_row)?;
        // Before this row's pointers overwrite anything, commit the row leaving the window.
        let committed = if self.window.len() == self.params.lag {
            let oldest = self.rows() - self.window.len();
            self.trace().into_iter().find(|e| e.row == oldest)
        } else {
            None
        };
        self.push_checked(chat_row.to_vec());
        Ok(committed)
    }

    /// [`OnlineSolver::push_row`] without re-tracing the row that leaves the window: returns
    /// that row's `ĉ` instead, if a row left.
    pub fn push_row_leaving(&mut self, chat_row: Vec<f32>) -> Result<Option<Vec<f32>>> {
        self.check_row(&chat_row)?;
        Ok(self.push_checked(chat_row))
    }

    fn check_row(&self, chat_row: &[f32]) -> Result<()> {
        if chat_row.len() != self.d {
            return Err(Error::Shape(format!(
                "a row has {} values, the map has {} references",
                chat_row.len(),
                self.d
            )));
        }
        if let Some(j) = chat_row.iter().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite {
                what: "similarity row",
                row: self.rows(),
                col: j,
                value: f64::from(chat_row[j]),
            });
        }
        Ok(())
    }

    /// The row step on a checked row: the leaving row (if the window is full) advances the
    /// window base, the new row the latest costs and the window.
    fn push_checked(&mut self, chat_row: Vec<f32>) -> Option<Vec<f32>> {
        let (back, left) = if self.window.len() == self.params.lag {
            let back = self.window.pop_front();
            let left = self.window_chat.pop_front();
            if let (Some(base), Some(row)) = (self.base.as_mut(), left.as_ref()) {
                step(&self.params, base, row, &mut self.scratch, None);
            }
            (back, left)
        } else {
            (None, None)
        };
        let mut back = back.unwrap_or_else(|| RowBack {
            x: vec![Back::SOURCE; self.d],
            h: vec![Back::SOURCE; self.d],
        });
        step(
            &self.params,
            &mut self.cur,
            &chat_row,
            &mut self.scratch,
            Some(&mut back),
        );
        self.window.push_back(back);
        self.window_chat.push_back(chat_row);
        left
    }

    /// The solver as it was before the first row of its lag window, with an empty window
    /// (`None` when the window base is not tracked). Pushing the window's `ĉ` rows into it
    /// gives back this solver exactly.
    pub fn base_image(&self) -> Option<OnlineSolver> {
        let base = self.base.as_ref()?;
        Some(OnlineSolver {
            params: self.params,
            d: self.d,
            cur: base.clone(),
            base: Some(base.clone()),
            window: VecDeque::with_capacity(self.params.lag + 1),
            window_chat: VecDeque::with_capacity(self.params.lag + 1),
            scratch: StepScratch::new(self.d),
        })
    }

    /// Appends the solver's exact state to `out` (see [`StateWriter`]): parameters, the two
    /// cost rows and the lag window. Scratch buffers and the window base are not written: a
    /// solver decoded with an empty window has its base (it is the latest costs), one decoded
    /// with a window has none. The size is `O(lag · D)`, independent of the rows consumed.
    pub fn encode(&self, out: &mut StateWriter) {
        let p = &self.params;
        out.u64(p.graph.fan_out as u64);
        out.bool(p.graph.horizontal);
        out.f64(p.graph.hidden_cost);
        out.u64(p.lag as u64);
        out.opt_f64(p.relocalization);
        out.u64(self.d as u64);
        out.u64(self.cur.rows as u64);
        out.f64s(&self.cur.x);
        out.f64s(&self.cur.h);
        out.u64(self.window.len() as u64);
        for (back, chat) in self.window.iter().zip(&self.window_chat) {
            for b in back.x.iter().chain(&back.h) {
                out.u32(b.0);
            }
            out.f32s(chat);
        }
    }

    /// Reads a state written by [`OnlineSolver::encode`], checking every invariant the solver
    /// relies on (so a corrupt state is an error, never a panic later).
    pub fn decode(r: &mut StateReader<'_>) -> Result<Self> {
        let fan_out = r.usize()?;
        let horizontal = r.bool()?;
        let hidden_cost = r.f64()?;
        let lag = r.usize()?;
        let relocalization = r.opt_f64()?;
        let params = OnlineParams {
            graph: GraphParams {
                fan_out,
                horizontal,
                hidden_cost,
            },
            lag,
            relocalization,
        };
        params
            .validate()
            .map_err(|e| corrupt(format!("solver parameters: {e}")))?;
        let d = r.usize()?;
        if r.remaining() / 16 < d {
            return Err(corrupt(format!(
                "state is truncated: {d} columns announced"
            )));
        }
        let mut solver =
            OnlineSolver::new(d, params).map_err(|e| corrupt(format!("solver size: {e}")))?;
        solver.cur.rows = r.usize()?;
        solver.cur.x = r.f64s(d)?;
        solver.cur.h = r.f64s(d)?;
        let window = r.usize()?;
        if window > lag || window > solver.cur.rows {
            return Err(corrupt(format!(
                "{window} rows in the lag window of {lag} after {} rows",
                solver.cur.rows
            )));
        }
        for _ in 0..window {
            let mut row = RowBack {
                x: Vec::with_capacity(d),
                h: Vec::with_capacity(d),
            };
            for k in 0..2 * d {
                let b = Back(r.u32()?);
                let col = k % d;
                let valid = match b.kind() {
                    0 => b.0 == 0,
                    1 => b.col() < d,
                    2 => b.0 == 2 && col > 0,
                    _ => false,
                };
                if !valid {
                    return Err(corrupt(format!("back-pointer {:#x} at column {col}", b.0)));
                }
                if k < d {
                    row.x.push(b);
                } else {
                    row.h.push(b);
                }
            }
            solver.window.push_back(row);
            solver.window_chat.push_back(r.f32s(d)?);
        }
        solver.base = (window == 0).then(|| solver.cur.clone());
        Ok(solver)
    }

    /// The best path over the rows still in the lag window, oldest first: one estimate per row.
    /// Empty before the first row.
    pub fn trace(&self) -> Vec<RowEstimate> {
        let Some(last) = self.window.len().checked_sub(1) else {
            return Vec::new();
        };
        let (x, h) = (&self.cur.x, &self.cur.h);
        // The best end node, picked as the offline solver's sink picks it: the lowest column of
        // the least `M = min(x, h)`, and in that column `h` only when strictly cheaper than `x`
        // (the rule the predecessors follow too), so ties end the path where offline does.
        let (mut col, mut hidden) = (0usize, false);
        let mut best = f64::INFINITY;
        for j in 0..self.d {
            let (m, h_wins) = if h[j] < x[j] {
                (h[j], true)
            } else {
                (x[j], false)
            };
            if m < best {
                best = m;
                (col, hidden) = (j, h_wins);
            }
        }
        let first_row = self.rows() - self.window.len();
        let mut out = Vec::with_capacity(self.window.len());
        let mut t = last;
        loop {
            let chat = &self.window_chat[t];
            let back = &self.window[t];
            let mut best_match: Option<(usize, f32)> = None;
            // Walk left along the horizontal run of this row.
            let entry = loop {
                let ptr = if hidden { back.h[col] } else { back.x[col] };
                if !hidden && best_match.is_none_or(|(_, s)| chat[col] > s) {
                    best_match = Some((col, chat[col]));
                }
                if ptr.kind() == Back::LEFT.kind() {
                    col -= 1;
                } else {
                    break ptr;
                }
            };
            out.push(RowEstimate {
                row: first_row + t,
                reference: best_match.map(|(j, _)| j),
                relocalized: entry.kind() == 1 && entry.teleport(),
            });
            if entry.kind() != 1 || t == 0 {
                break;
            }
            col = entry.col();
            hidden = entry.hidden();
            t -= 1;
        }
        out.reverse();
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::{solve, HiddenCost, SolverParams};
    use crate::Matrix;
    use proptest::prelude::*;

    fn params(k: usize, horizontal: bool, w: f64, lag: usize, reloc: Option<f64>) -> OnlineParams {
        OnlineParams {
            graph: GraphParams {
                fan_out: k,
                horizontal,
                hidden_cost: w,
            },
            lag,
            relocalization: reloc,
        }
    }

    /// The offline solver's answer for the last row of `chat[..rows]`: its best-`ĉ` match.
    fn offline_last(
        chat: &Matrix,
        rows: usize,
        k: usize,
        horizontal: bool,
        w: f64,
    ) -> Option<usize> {
        let prefix = Matrix::from_vec(
            rows,
            chat.cols(),
            chat.as_slice()[..rows * chat.cols()].to_vec(),
        )
        .unwrap();
        let sp = SolverParams {
            fan_out: k,
            hidden_cost: HiddenCost::Fixed(w),
            horizontal,
            ..SolverParams::default()
        };
        let solution = solve(&prefix, &sp).unwrap();
        let last = solution.hypotheses[0].rows.last().unwrap();
        last.matches
            .iter()
            .max_by(|a, b| a.similarity.total_cmp(&b.similarity))
            .map(|m| m.reference)
    }

    /// Feeds every row of `chat` to a solver whose lag window holds them all (no row leaves
    /// it) and checks that the traced path is the offline `F = 1` path.
    fn full_window_trace_is_offline_path(
        chat: &Matrix,
        k: usize,
        horizontal: bool,
        w: f64,
    ) -> std::result::Result<(), TestCaseError> {
        let (q, d) = (chat.rows(), chat.cols());
        let mut online = OnlineSolver::new(d, params(k, horizontal, w, q, None)).unwrap();
        for i in 0..q {
            prop_assert_eq!(online.push_row(chat.row(i)).unwrap(), None);
        }
        let sp = SolverParams {
            fan_out: k,
            hidden_cost: HiddenCost::Fixed(w),
            horizontal,
            ..SolverParams::default()
        };
        let offline = solve(chat, &sp).unwrap();
        let offline_refs: Vec<Option<usize>> = offline.hypotheses[0]
            .rows
            .iter()
            .map(|r| {
                r.matches
                    .iter()
                    .max_by(|a, b| a.similarity.total_cmp(&b.similarity))
                    .map(|m| m.reference)
            })
            .collect();
        let online_refs: Vec<Option<usize>> = online.trace().iter().map(|e| e.reference).collect();
        prop_assert_eq!(online_refs, offline_refs);
        Ok(())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]
        /// For F = 1 without relocalization, the estimate for the latest row equals the offline
        /// solve of the rows so far, after every row, whatever the lag window.
        #[test]
        fn latest_estimate_equals_offline_solve(
            q in 1usize..12, d in 1usize..10, vals in prop::collection::vec(-0.2f32..3.0, 120),
            k in 0usize..4, horizontal: bool, w in 0.3f64..2.5, lag in 1usize..6,
        ) {
            let chat = Matrix::from_vec(q, d, vals[..q * d].to_vec()).unwrap();
            let mut online = OnlineSolver::new(d, params(k, horizontal, w, lag, None)).unwrap();
            for i in 0..q {
                online.push_row(chat.row(i)).unwrap();
                let trace = online.trace();
                prop_assert_eq!(trace.len(), (i + 1).min(lag));
                let latest = trace.last().unwrap();
                prop_assert_eq!(latest.row, i);
                prop_assert_eq!(latest.reference, offline_last(&chat, i + 1, k, horizontal, w), "row {}", i);
            }
        }

        /// With a lag window as long as the trip, the traced path is the offline path.
        #[test]
        fn full_window_trace_equals_offline_path(
            q in 1usize..10, d in 1usize..9, vals in prop::collection::vec(0.05f32..3.0, 90),
            k in 0usize..4, horizontal: bool, w in 0.3f64..2.5,
        ) {
            let chat = Matrix::from_vec(q, d, vals[..q * d].to_vec()).unwrap();
            full_window_trace_is_offline_path(&chat, k, horizontal, w)?;
        }

        /// The same on matrices of a few exactly representable values, where costs tie all
        /// the time (also along hidden stretches), for fan-outs of both window scans: the
        /// online row step and the offline kernel share the window minimum and its tie rule
        /// (`crate::window`), so they pick the same path.
        #[test]
        fn full_window_trace_equals_offline_path_when_costs_tie(
            q in 1usize..10, d in 1usize..14,
            vals in prop::collection::vec(prop::sample::select(vec![0.0f32, 0.5, 1.0, 2.0, 4.0]), 130),
            k in 0usize..12, horizontal: bool,
            w in prop::sample::select(vec![0.5f64, 1.0, 2.0, 4.0]),
        ) {
            let chat = Matrix::from_vec(q, d, vals[..q * d].to_vec()).unwrap();
            full_window_trace_is_offline_path(&chat, k, horizontal, w)?;
        }
    }

    #[test]
    fn rows_leaving_the_window_are_committed_in_order() {
        let d = 6;
        let mut online = OnlineSolver::new(d, params(1, true, 2.0, 3, None)).unwrap();
        let mut committed = Vec::new();
        for i in 0..6 {
            let row: Vec<f32> = (0..d).map(|j| if j == i { 3.0 } else { 0.5 }).collect();
            if let Some(c) = online.push_row(&row).unwrap() {
                committed.push(c);
            }
        }
        assert_eq!(
            committed
                .iter()
                .map(|c| (c.row, c.reference))
                .collect::<Vec<_>>(),
            vec![(0, Some(0)), (1, Some(1)), (2, Some(2))]
        );
        assert_eq!(
            online
                .trace()
                .iter()
                .map(|e| e.reference)
                .collect::<Vec<_>>(),
            vec![Some(3), Some(4), Some(5)]
        );
    }

    #[test]
    fn relocalization_finds_a_jump_back_that_the_forward_graph_cannot() {
        // 20 columns; rows 0..10 follow the diagonal 10..20, rows 10..20 jump back to 0..10.
        let d = 20;
        let row_for = |i: usize| -> Vec<f32> {
            let truth = if i < 10 { 10 + i } else { i - 10 };
            (0..d).map(|j| if j == truth { 2.5 } else { 0.9 }).collect()
        };
        let mut forward_only = OnlineSolver::new(d, params(2, true, 1.5, 50, None)).unwrap();
        let mut reloc = OnlineSolver::new(d, params(2, true, 1.5, 50, Some(3.0))).unwrap();
        for i in 0..20 {
            forward_only.push_row(&row_for(i)).unwrap();
            reloc.push_row(&row_for(i)).unwrap();
        }
        let trace = reloc.trace();
        assert_eq!(trace.last().unwrap().reference, Some(9));
        assert!(
            trace.iter().any(|e| e.relocalized && e.row >= 10),
            "{trace:?}"
        );
        // The paper's graph cannot go back: its latest estimate is not the true place.
        assert_ne!(forward_only.trace().last().unwrap().reference, Some(9));
    }

    #[test]
    fn bad_rows_and_parameters_are_rejected() {
        let mut online = OnlineSolver::new(3, params(1, true, 1.0, 4, None)).unwrap();
        assert!(matches!(online.push_row(&[1.0, 2.0]), Err(Error::Shape(_))));
        assert!(matches!(
            online.push_row(&[1.0, f32::NAN, 2.0]),
            Err(Error::NonFinite { col: 1, .. })
        ));
        assert_eq!(online.rows(), 0);
        assert!(OnlineSolver::new(0, params(1, true, 1.0, 4, None)).is_err());
        assert!(OnlineSolver::new(3, params(1, true, 1.0, 0, None)).is_err());
        assert!(OnlineSolver::new(3, params(1, true, -1.0, 4, None)).is_err());
        assert!(OnlineSolver::new(3, params(1, true, 1.0, 4, Some(f64::NAN))).is_err());
    }
}
