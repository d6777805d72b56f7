//! Pieces of the graph model shared by every solver: the set of blocked matching nodes, input
//! checks, node costs, and the conversion of a node path into a [`Hypothesis`].
//!
//! A path is a list of [`Step`]s in visiting order. Within one row a path visits a run of
//! consecutive columns of a single kind (there are no edges between `x` and `h` of the same
//! row), so a row is either matched (a run of matching nodes) or hidden. Its cost is the sum of
//! the costs of the edges it takes: `1/ĉ` for every matching node, `W` for the first hidden node
//! of a row (entered by a source or forward edge) and `0` for the following hidden nodes of that
//! row (free horizontal edges).

use super::{Hypothesis, Match, RowAssignment, MAX_FAN_OUT};
use crate::{Error, Matrix, Result};

/// A set of matching nodes `x_ij` that a solver must not use (e.g. those taken by earlier
/// hypotheses). A bitset over the `Q x D` grid.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Blocked {
    rows: usize,
    cols: usize,
    bits: Vec<u64>,
}

impl Blocked {
    /// An empty set for a `rows x cols` similarity matrix.
    pub fn new(rows: usize, cols: usize) -> Self {
        Blocked {
            rows,
            cols,
            bits: vec![0; (rows * cols).div_ceil(64)],
        }
    }

    /// Number of rows of the grid.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Number of columns of the grid.
    pub fn cols(&self) -> usize {
        self.cols
    }

    /// Blocks `x_ij`. Panics when `(i, j)` is outside the grid, like slice indexing.
    pub fn block(&mut self, i: usize, j: usize) {
        assert!(
            i < self.rows && j < self.cols,
            "({i}, {j}) outside the grid"
        );
        let n = i * self.cols + j;
        self.bits[n / 64] |= 1 << (n % 64);
    }

    /// Whether `x_ij` is blocked (false outside the grid).
    #[inline]
    pub fn is_blocked(&self, i: usize, j: usize) -> bool {
        if i >= self.rows || j >= self.cols {
            return false;
        }
        let n = i * self.cols + j;
        self.bits[n / 64] & (1 << (n % 64)) != 0
    }

    /// Calls `f(j)` for every blocked `x_ij` of row `i` with `lo <= j < hi`, in increasing `j`,
    /// at the cost of one word test per 64 columns.
    pub(crate) fn for_each_in_row(&self, i: usize, lo: usize, hi: usize, mut f: impl FnMut(usize)) {
        let row0 = i * self.cols;
        let (mut n, end) = (row0 + lo, row0 + hi.min(self.cols));
        while n < end {
            let word = self.bits[n / 64] >> (n % 64);
            if word == 0 {
                n = (n / 64 + 1) * 64;
                continue;
            }
            n += word.trailing_zeros() as usize;
            if n >= end {
                break;
            }
            f(n - row0);
            n += 1;
        }
    }

    /// Blocks every matching node used by `hypothesis`. Panics when one lies outside the grid.
    pub fn block_hypothesis(&mut self, hypothesis: &Hypothesis) {
        for row in &hypothesis.rows {
            for m in &row.matches {
                self.block(row.query, m.reference);
            }
        }
    }

    /// Number of blocked nodes.
    pub fn len(&self) -> usize {
        self.bits.iter().map(|b| b.count_ones() as usize).sum()
    }

    /// Whether no node is blocked.
    pub fn is_empty(&self) -> bool {
        self.bits.iter().all(|&b| b == 0)
    }
}

/// Which node of a cell a path visits.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Kind {
    /// The matching node `x_ij`.
    Match,
    /// The hidden node `h_ij`.
    Hidden,
}

/// One node of a path.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Step {
    pub row: usize,
    pub col: usize,
    pub kind: Kind,
}

/// Cost of the matching node for similarity `v`: `1/v`, or `+inf` (unusable) when `v <= 0`.
#[inline]
pub(crate) fn match_cost(v: f32) -> f64 {
    if v > 0.0 {
        1.0 / f64::from(v)
    } else {
        f64::INFINITY
    }
}

/// Fails on an empty or non-finite similarity matrix.
pub(crate) fn check_matrix(chat: &Matrix) -> Result<()> {
    if chat.rows() == 0 || chat.cols() == 0 {
        return Err(Error::Empty(format!(
            "the similarity matrix is {}x{}; the solver needs at least one query and one reference",
            chat.rows(),
            chat.cols()
        )));
    }
    chat.check_finite("similarity matrix")
}

/// Fails unless `fan_out` is at most [`MAX_FAN_OUT`]. The one check of the fan-out cap: the
/// offline solver, the online solver and trip parameters all call it.
pub fn check_fan_out(fan_out: usize) -> Result<()> {
    if fan_out > MAX_FAN_OUT {
        return Err(Error::param(
            "fan_out",
            format!("must be at most {MAX_FAN_OUT}, got {fan_out}"),
        ));
    }
    Ok(())
}

/// Largest accepted hidden cost `W`. A path's cost adds `W` once per hidden run, so an
/// unbounded `W` overflows to infinity (1e308 with 8 flows did), and every path then costs
/// the same; 1e12 already means "never hidden" next to match costs `1/ĉ` of real data, and
/// keeps every cost finite for any realistic sequence length and flow count.
pub const MAX_HIDDEN_COST: f64 = 1e12;

/// Fails unless `w` is a finite number in `(0, MAX_HIDDEN_COST]`. The one check of the hidden
/// cost: the offline solver, the confidence, the online solver and trip parameters all call
/// it.
pub fn check_hidden_cost(w: f64) -> Result<()> {
    if !(w.is_finite() && w > 0.0 && w <= MAX_HIDDEN_COST) {
        return Err(Error::param(
            "hidden_cost",
            format!("must be a finite number > 0 and at most {MAX_HIDDEN_COST:e}, got {w}"),
        ));
    }
    Ok(())
}

/// All checks of the public low-level entry points ([`super::shortest_path()`],
/// [`super::row_alternatives`]).
pub(crate) fn check_inputs(
    chat: &Matrix,
    fan_out: usize,
    w: f64,
    blocked: Option<&Blocked>,
) -> Result<()> {
    check_matrix(chat)?;
    check_fan_out(fan_out)?;
    check_hidden_cost(w)?;
    if let Some(b) = blocked {
        if (b.rows(), b.cols()) != (chat.rows(), chat.cols()) {
            return Err(Error::Shape(format!(
                "the blocked set is {}x{} but the similarity matrix is {}x{}",
                b.rows(),
                b.cols(),
                chat.rows(),
                chat.cols()
            )));
        }
    }
    Ok(())
}

/// Turns a node path (visiting order) into a hypothesis, recomputing its cost from the nodes.
pub(crate) fn hypothesis_from_steps(
    chat: &Matrix,
    w: f64,
    steps: &[Step],
    rank: usize,
) -> Hypothesis {
    let mut rows: Vec<RowAssignment> = (0..chat.rows())
        .map(|query| RowAssignment {
            query,
            matches: Vec::new(),
        })
        .collect();
    let mut cost = 0.0;
    let mut prev: Option<Step> = None;
    for &s in steps {
        match s.kind {
            Kind::Match => {
                let similarity = chat.get(s.row, s.col);
                cost += match_cost(similarity);
                rows[s.row].matches.push(Match {
                    reference: s.col,
                    similarity,
                });
            }
            Kind::Hidden => {
                let horizontal = prev.is_some_and(|p| p.row == s.row);
                if !horizontal {
                    cost += w;
                }
            }
        }
        prev = Some(s);
    }
    Hypothesis { rank, cost, rows }
}

/// The stopping rule: keeps the first hypothesis and stops before the first later one whose
/// hidden fraction exceeds `limit`.
pub(crate) fn apply_stop_rule(mut hyps: Vec<Hypothesis>, limit: Option<f64>) -> Vec<Hypothesis> {
    if let Some(f) = limit {
        if let Some(cut) = hyps.iter().skip(1).position(|h| h.hidden_fraction() > f) {
            hyps.truncate(cut + 1);
        }
    }
    hyps
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blocked_set_round_trips() {
        let mut b = Blocked::new(3, 70);
        assert!(b.is_empty());
        b.block(2, 69);
        b.block(0, 0);
        assert!(b.is_blocked(2, 69) && b.is_blocked(0, 0));
        assert!(!b.is_blocked(1, 5) && !b.is_blocked(9, 9));
        assert_eq!(b.len(), 2);
    }

    #[test]
    fn for_each_in_row_lists_the_blocked_columns_of_a_range() {
        let mut b = Blocked::new(3, 150);
        let cols = [0, 1, 63, 64, 65, 127, 128, 149];
        for &j in &cols {
            b.block(1, j);
        }
        b.block(0, 149);
        b.block(2, 0);
        let list = |lo, hi| {
            let mut v = Vec::new();
            b.for_each_in_row(1, lo, hi, |j| v.push(j));
            v
        };
        assert_eq!(list(0, 150), cols);
        assert_eq!(list(1, 128), vec![1, 63, 64, 65, 127]);
        assert_eq!(list(66, 127), Vec::<usize>::new());
        assert_eq!(list(149, 150), vec![149]);
        let mut v = Vec::new();
        b.for_each_in_row(0, 0, 150, |j| v.push(j));
        assert_eq!(v, vec![149]);
    }

    #[test]
    fn hypothesis_cost_charges_w_once_per_hidden_row() {
        let chat = Matrix::from_rows(&[vec![2.0, 4.0, 1.0], vec![1.0, 1.0, 1.0]]).unwrap();
        let steps = [
            Step {
                row: 0,
                col: 0,
                kind: Kind::Match,
            },
            Step {
                row: 0,
                col: 1,
                kind: Kind::Match,
            },
            Step {
                row: 1,
                col: 1,
                kind: Kind::Hidden,
            },
            Step {
                row: 1,
                col: 2,
                kind: Kind::Hidden,
            },
        ];
        let h = hypothesis_from_steps(&chat, 3.0, &steps, 1);
        assert!((h.cost - (0.5 + 0.25 + 3.0)).abs() < 1e-12);
        assert_eq!(h.rows[0].matches.len(), 2);
        assert!(h.rows[1].matches.is_empty());
        assert_eq!(h.hidden_fraction(), 0.5);
    }

    #[test]
    fn check_inputs_rejects_bad_inputs() {
        let chat = Matrix::from_rows(&[vec![1.0, f32::NAN]]).unwrap();
        assert!(matches!(
            check_inputs(&chat, 1, 1.0, None),
            Err(Error::NonFinite { row: 0, col: 1, .. })
        ));
        let ok = Matrix::from_rows(&[vec![1.0, 2.0]]).unwrap();
        assert!(matches!(
            check_inputs(&Matrix::zeros(0, 3), 1, 1.0, None),
            Err(Error::Empty(_))
        ));
        assert!(check_inputs(&ok, MAX_FAN_OUT + 1, 1.0, None).is_err());
        assert!(check_inputs(&ok, 1, 0.0, None).is_err());
        assert!(check_inputs(&ok, 1, f64::NAN, None).is_err());
        let err = check_inputs(&ok, 1, 1.0, Some(&Blocked::new(2, 2))).unwrap_err();
        assert!(err.to_string().contains("blocked set is 2x2"), "{err}");
    }
}
