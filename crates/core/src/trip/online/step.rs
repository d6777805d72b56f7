//! The row step of the online `F = 1` solver: from the cheapest costs into every matching
//! (`x`) and hidden (`h`) node of one row, those of the next row given its `ĉ` (the window
//! minimum over `fan_out` predecessors with the offline kernel's tie rule, the optional
//! relocalization edge from the row's cheapest node, then the horizontal moves), and the
//! back-pointers that let [`super::OnlineSolver`] re-trace its lag window.
//!
//! Why apart: this is the graph of spec §2 one row at a time, the part that must agree with
//! the offline solver; the solver around it is bookkeeping (the lag window, the window base,
//! commits, the stored state). `O(D)` per row, no allocation (buffers in [`StepScratch`]).

use crate::solver::match_cost;
use crate::window::{trailing_min_offsets, MonoDeque, Scan};

use super::OnlineParams;

/// Where the best path into a node came from, packed into a `u32`:
/// bits 0-1 kind (0 source, 1 previous row, 2 left neighbour), bit 2 previous node is hidden,
/// bit 3 the step was a relocalization, bits 4.. the previous row's column.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Back(pub(super) u32);

impl Back {
    pub(super) const SOURCE: Back = Back(0);
    pub(super) const LEFT: Back = Back(2);
    pub(super) const MAX_COLUMN: usize = (u32::MAX >> 4) as usize;

    pub(super) fn prev(col: usize, hidden: bool, teleport: bool) -> Back {
        Back(1 | (u32::from(hidden) << 2) | (u32::from(teleport) << 3) | ((col as u32) << 4))
    }
    pub(super) fn kind(self) -> u32 {
        self.0 & 3
    }
    pub(super) fn hidden(self) -> bool {
        self.0 & 4 != 0
    }
    pub(super) fn teleport(self) -> bool {
        self.0 & 8 != 0
    }
    pub(super) fn col(self) -> usize {
        (self.0 >> 4) as usize
    }
}

/// Back-pointers of one row.
#[derive(Clone)]
pub(super) struct RowBack {
    pub(super) x: Vec<Back>,
    pub(super) h: Vec<Back>,
}

/// The cost rows of the DP after some number of rows: the cheapest path from the source to
/// every matching (`x`) and hidden (`h`) node of the last row consumed.
#[derive(Clone, PartialEq)]
pub(super) struct Costs {
    pub(super) rows: usize,
    pub(super) x: Vec<f64>,
    pub(super) h: Vec<f64>,
}

impl Costs {
    pub(super) fn new(d: usize) -> Self {
        Costs {
            rows: 0,
            x: vec![0.0; d],
            h: vec![0.0; d],
        }
    }
}

/// Scratch of one row step (not state).
#[derive(Clone, Default)]
pub(super) struct StepScratch {
    /// `min(x, h)` of the previous row per column, and which node it is (`column << 1 | hidden`).
    best_prev: Vec<f64>,
    best_arg: Vec<u32>,
    /// The predecessor value of each column (window minimum of `best_prev`, or the jump), and
    /// the window offset of its argmin.
    pred: Vec<f64>,
    pred_off: Vec<u64>,
    dq: MonoDeque,
}

impl StepScratch {
    pub(super) fn new(d: usize) -> Self {
        StepScratch {
            best_prev: vec![0.0; d],
            best_arg: vec![0; d],
            pred: vec![0.0; d],
            pred_off: vec![0; d],
            dq: MonoDeque::default(),
        }
    }

    pub(super) fn heap_bytes(&self) -> usize {
        (self.best_prev.capacity() + self.pred.capacity() + self.pred_off.capacity()) * 8
            + self.best_arg.capacity() * 4
            + self.dq.heap_bytes()
    }
}

/// One row step of the DP on `c` (the costs after `c.rows` rows) with the row `ĉ`, writing
/// the new row's back-pointers into `back` when given (the window base needs values only).
// The row update reads neighbouring columns; indices say that more plainly.
#[allow(clippy::needless_range_loop)]
pub(super) fn step(
    params: &OnlineParams,
    c: &mut Costs,
    chat_row: &[f32],
    s: &mut StepScratch,
    mut back: Option<&mut RowBack>,
) {
    let d = chat_row.len();
    let k = params.graph.fan_out;
    let w = params.graph.hidden_cost;
    if c.rows == 0 {
        s.pred.fill(0.0);
        if let Some(b) = back.as_deref_mut() {
            b.x.fill(Back::SOURCE);
            b.h.fill(Back::SOURCE);
        }
    } else {
        // Predecessor value of each column: the cheaper of x/h, argument encodes (col, hidden).
        for j in 0..d {
            (s.best_prev[j], s.best_arg[j]) = if c.x[j] <= c.h[j] {
                (c.x[j], (j as u32) << 1)
            } else {
                (c.h[j], ((j as u32) << 1) | 1)
            };
        }
        // The window minimum of the offline kernel, with its tie rule (latest column).
        let strategy = Scan::for_fan_out(k);
        s.dq.start(&s.best_prev, 0, k);
        trailing_min_offsets(
            &s.best_prev,
            0,
            k,
            strategy,
            &mut s.pred,
            &mut s.pred_off,
            &mut s.dq,
        );
        let teleport =
            params.relocalization.map(|r| {
                let (v, arg) = s.best_prev.iter().zip(&s.best_arg).fold(
                    (f64::INFINITY, 0),
                    |a, (&v, &arg)| {
                        if v < a.0 {
                            (v, arg)
                        } else {
                            a
                        }
                    },
                );
                (v + r, arg)
            });
        match back.as_deref_mut() {
            Some(b) => {
                for j in 0..d {
                    let arg = s.best_arg[j - s.pred_off[j] as usize];
                    let mut ptr = Back::prev((arg >> 1) as usize, arg & 1 == 1, false);
                    let mut val = s.pred[j];
                    if let Some((tv, targ)) = teleport {
                        if tv < val {
                            val = tv;
                            ptr = Back::prev((targ >> 1) as usize, targ & 1 == 1, true);
                        }
                    }
                    s.pred[j] = val;
                    b.x[j] = ptr;
                    b.h[j] = ptr;
                }
            }
            None => {
                if let Some((tv, _)) = teleport {
                    for p in s.pred.iter_mut() {
                        if tv < *p {
                            *p = tv;
                        }
                    }
                }
            }
        }
    }
    for j in 0..d {
        let p = s.pred[j];
        c.x[j] = p + match_cost(chat_row[j]);
        c.h[j] = p + w;
    }
    if params.graph.horizontal {
        for j in 1..d {
            let left = c.x[j - 1] + match_cost(chat_row[j]);
            if left < c.x[j] {
                c.x[j] = left;
                if let Some(b) = back.as_deref_mut() {
                    b.x[j] = Back::LEFT;
                }
            }
            if c.h[j - 1] < c.h[j] {
                c.h[j] = c.h[j - 1];
                if let Some(b) = back.as_deref_mut() {
                    b.h[j] = Back::LEFT;
                }
            }
        }
    }
    c.rows += 1;
}
