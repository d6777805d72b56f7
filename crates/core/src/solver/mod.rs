//! The data-association graph of the flow paper (Section III-B) and its solvers.
//!
//! For query row `i` and reference column `j` there is a matching node `x_ij` (cost `1/ĉ_ij`,
//! unusable when `ĉ_ij <= 0`) and a hidden node `h_ij` (cost `W`). Forward edges go from row `i`
//! column `j` to row `i+1` columns `j..=j+K`; optional horizontal edges go from `(i, j)` to
//! `(i, j+1)` within a row. Following `spec.md` §2 (the one deliberate correction of the paper),
//! a horizontal step *into a matching node* costs that node's matching cost; horizontal steps
//! between hidden nodes are free. Every edge into a node carries that node's cost, so a path's
//! cost is the sum of the costs of the nodes it visits.
//!
//! * `F = 1`: the shortest source-sink path, by dynamic programming over the DAG in `O(Q·D)`.
//! * `F > 1` greedy (the paper): repeat the shortest path, blocking used matching nodes.
//! * `F > 1` exact: successive shortest paths with potentials on the residual graph.
//!
//! Matching nodes have capacity 1 (node-disjoint flows); hidden nodes carry any number of flows.
//!
//! Code map: the graph helpers (blocked set, input checks, path -> [`Hypothesis`]) live in
//! `graph.rs`, the `F = 1` dynamic programme in `shortest_path.rs` (its row step, the hot loop,
//! in `kernel.rs`; the confidence reuses it), greedy and exact `F > 1` in
//! `greedy.rs` / `exact.rs`, the whole graph's min-marginals along a hypothesis in
//! `marginals.rs` (the confidences read local forms of them), and the test-only
//! reference solvers (generic min-cost flow, brute force) in `reference.rs`.
//!
//! Invariants: every solver returns hypotheses with one [`RowAssignment`] per query row, matches
//! in increasing column order, never on an unusable (`ĉ <= 0`) or blocked matching node, and a
//! `cost` equal to the sum of the path's edge costs (recomputed in `f64` from the path).

mod exact;
mod graph;
mod greedy;
mod kernel;
mod marginals;
#[cfg(test)]
mod reference;
mod shortest_path;

/// Node cost of a matching node: `1/ĉ`, or `+inf` when `ĉ <= 0` (unusable). Every solver,
/// the confidence and the online solver use this one definition.
pub(crate) use graph::match_cost;
pub use graph::{check_fan_out, check_hidden_cost, Blocked, MAX_HIDDEN_COST};
pub(crate) use kernel::{forward_values_row, Scratch as RowScratch};
pub use marginals::{row_alternatives, RowAlternatives};
pub use shortest_path::shortest_path;

use crate::{Error, Matrix, Result};

/// How the hidden (non-match) cost `W` is chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum HiddenCost {
    /// Derived from the similarity matrix at hand (see [`auto_hidden_cost`]).
    Auto,
    /// A fixed value, > 0.
    Fixed(f64),
}

/// Parameters of the graph and the solver. Validate with [`SolverParams::validate`].
#[derive(Clone, Debug, PartialEq)]
pub struct SolverParams {
    /// `K`: forward edges from column `j` reach columns `j..=j+K` of the next row.
    pub fan_out: usize,
    /// `W`: the cost of a hidden node.
    pub hidden_cost: HiddenCost,
    /// `F`: the number of flows (route hypotheses), >= 1.
    pub flows: usize,
    /// Solve `F > 1` exactly (min-cost flow) instead of greedily.
    pub exact: bool,
    /// Horizontal edges within a row.
    pub horizontal: bool,
    /// The paper's stopping rule: stop adding flows once a path's fraction of hidden rows
    /// exceeds this value (the path that exceeds it is not reported). `None` keeps all `F`.
    pub stop_hidden_fraction: Option<f64>,
}

impl Default for SolverParams {
    fn default() -> Self {
        SolverParams {
            fan_out: 4,
            hidden_cost: HiddenCost::Auto,
            flows: 1,
            exact: false,
            horizontal: true,
            stop_hidden_fraction: None,
        }
    }
}

/// Largest accepted fan-out; larger values make the graph meaningless for a route.
pub const MAX_FAN_OUT: usize = 1024;
/// Largest accepted number of flows.
pub const MAX_FLOWS: usize = 64;

impl SolverParams {
    /// Checks every parameter's range.
    pub fn validate(&self) -> Result<()> {
        check_fan_out(self.fan_out)?;
        if let HiddenCost::Fixed(w) = self.hidden_cost {
            check_hidden_cost(w)?;
        }
        if self.flows == 0 || self.flows > MAX_FLOWS {
            return Err(Error::param(
                "flows",
                format!("must be between 1 and {MAX_FLOWS}, got {}", self.flows),
            ));
        }
        if let Some(f) = self.stop_hidden_fraction {
            if !(f.is_finite() && (0.0..=1.0).contains(&f)) {
                return Err(Error::param(
                    "stop_hidden_fraction",
                    format!("must be within [0, 1], got {f}"),
                ));
            }
        }
        Ok(())
    }
}

/// One matched reference image in a row of a hypothesis.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct Match {
    /// Reference (column) index `j`.
    #[cfg_attr(feature = "serde", serde(rename = "ref"))]
    pub reference: usize,
    /// `ĉ_ij` of the matching node.
    pub similarity: f32,
}

/// What a hypothesis says about one query row.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct RowAssignment {
    /// Query (row) index `i`.
    pub query: usize,
    /// Matched references in increasing order (several when horizontal edges were used);
    /// empty when the row is hidden.
    pub matches: Vec<Match>,
}

/// A route hypothesis: one source-to-sink path.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct Hypothesis {
    /// 1-based rank (order found for greedy, increasing cost for exact).
    pub rank: usize,
    /// Sum of the costs of the nodes on the path.
    pub cost: f64,
    /// One entry per query row, in row order.
    pub rows: Vec<RowAssignment>,
}

impl Hypothesis {
    /// Fraction of rows that are hidden.
    pub fn hidden_fraction(&self) -> f64 {
        if self.rows.is_empty() {
            return 0.0;
        }
        let hidden = self.rows.iter().filter(|r| r.matches.is_empty()).count();
        hidden as f64 / self.rows.len() as f64
    }
}

/// The result of [`solve`].
#[derive(Clone, Debug, PartialEq)]
pub struct Solution {
    /// The hidden cost `W` actually used (resolved when [`HiddenCost::Auto`]).
    pub hidden_cost: f64,
    /// Ranked hypotheses.
    pub hypotheses: Vec<Hypothesis>,
}

impl Solution {
    /// Sum of the hypotheses' costs.
    pub fn total_cost(&self) -> f64 {
        self.hypotheses.iter().map(|h| h.cost).sum()
    }
}

/// The quantile of the usable `ĉ` values that [`auto_hidden_cost`] turns into `W`.
pub const AUTO_HIDDEN_QUANTILE: f64 = 0.02;

/// Most values [`auto_hidden_cost`] looks at (an evenly strided sample of the matrix).
const AUTO_HIDDEN_SAMPLE: usize = 1 << 20;

/// Resolves `W` from the matrix at hand: `W = 1 / q`, where `q` is the 2nd percentile
/// ([`AUTO_HIDDEN_QUANTILE`]) of the usable (`> 0`) entries of `ĉ`.
///
/// Meaning: a hidden node is cheaper than a matching node exactly when that node's similarity
/// is among the lowest 2 % of all query/reference pairs. A query that is off the map (its whole
/// row far below the column means) goes hidden; an ordinary weak match does not. Because it is a
/// quantile of the matrix itself, it follows the spread of the descriptor's similarities (HOG,
/// CNN, other data) instead of being a constant tuned to one dataset. On the Nordland dev split
/// (HOG, 8 px cells) it gives `W ≈ 1.37`, inside the 1.05-3 range where AP is flat; below about
/// 0.95 the path goes hidden everywhere. With no usable entry it returns 1.
pub fn auto_hidden_cost(chat: &Matrix) -> f64 {
    let values = chat.as_slice();
    let stride = values.len().div_ceil(AUTO_HIDDEN_SAMPLE).max(1);
    let mut sample: Vec<f32> = values
        .iter()
        .step_by(stride)
        .copied()
        .filter(|v| *v > 0.0 && v.is_finite())
        .collect();
    if sample.is_empty() {
        return 1.0;
    }
    let k = ((sample.len() - 1) as f64 * AUTO_HIDDEN_QUANTILE).round() as usize;
    let (_, q, _) = sample.select_nth_unstable_by(k, f32::total_cmp);
    1.0 / f64::from(*q)
}

/// Solves the graph on the normalised similarity matrix `chat` (`ĉ`, Q x D).
///
/// `F = 1` is the shortest path; `F > 1` is greedy (ranked by order found) unless
/// `params.exact`, which solves the true min-cost flow (ranked by increasing cost). The stopping
/// rule `stop_hidden_fraction` never drops the first (rank 1) hypothesis; it stops before the
/// first later hypothesis whose hidden fraction exceeds the limit.
///
/// Fails on an empty matrix, a non-finite entry or an invalid parameter.
pub fn solve(chat: &Matrix, params: &SolverParams) -> Result<Solution> {
    params.validate()?;
    graph::check_matrix(chat)?;
    let w = match params.hidden_cost {
        HiddenCost::Fixed(w) => w,
        HiddenCost::Auto => auto_hidden_cost(chat),
    };
    check_hidden_cost(w)?;
    let hypotheses = if params.flows > 1 && params.exact {
        exact::min_cost_flow(chat, params.fan_out, params.horizontal, w, params.flows)?
    } else {
        greedy::greedy_paths(
            chat,
            params.fan_out,
            params.horizontal,
            w,
            params.flows,
            params.stop_hidden_fraction,
        )
    };
    let hypotheses = graph::apply_stop_rule(hypotheses, params.stop_hidden_fraction);
    Ok(Solution {
        hidden_cost: w,
        hypotheses,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixed(flows: usize, exact: bool) -> SolverParams {
        SolverParams {
            hidden_cost: HiddenCost::Fixed(1.2),
            flows,
            exact,
            ..SolverParams::default()
        }
    }

    #[test]
    fn the_largest_hidden_cost_keeps_every_cost_finite() {
        // 1e308 with 8 flows once overflowed to an infinite (JSON null) total cost.
        let chat = Matrix::from_vec(6, 5, vec![0.01f32; 30]).unwrap();
        for exact in [false, true] {
            let params = SolverParams {
                hidden_cost: HiddenCost::Fixed(graph::MAX_HIDDEN_COST),
                flows: 8,
                exact,
                ..SolverParams::default()
            };
            let s = solve(&chat, &params).unwrap();
            assert!(s.total_cost().is_finite(), "{}", s.total_cost());
            assert!(s.hypotheses.iter().all(|h| h.cost.is_finite()));
            let too_big = SolverParams {
                hidden_cost: HiddenCost::Fixed(1e308),
                ..params
            };
            let e = solve(&chat, &too_big).unwrap_err().to_string();
            assert!(e.contains("hidden_cost") && e.contains("1e12"), "{e}");
        }
    }

    fn route(h: &Hypothesis) -> Vec<Option<usize>> {
        h.rows
            .iter()
            .map(|r| r.matches.first().map(|m| m.reference))
            .collect()
    }

    #[test]
    fn solve_with_one_flow_is_the_shortest_path() {
        let chat = Matrix::from_rows(&[vec![3.0, 0.5, 0.2], vec![0.4, 3.0, 0.5]]).unwrap();
        for exact in [false, true] {
            let sol = solve(&chat, &fixed(1, exact)).unwrap();
            let sp = shortest_path(&chat, 4, true, 1.2, None).unwrap();
            assert_eq!(sol.hypotheses, vec![sp]);
            assert_eq!(sol.hidden_cost, 1.2);
            assert!((sol.total_cost() - (1.0 / 3.0 + 1.0 / 3.0)).abs() < 1e-9);
        }
    }

    #[test]
    fn new_places_come_out_hidden() {
        // Rows 3..6 are a detour through places the reference never saw (mediocre similarity
        // everywhere); the route then resumes where it left the reference.
        let mut rows = Vec::new();
        for i in 0..9 {
            let mut r = vec![0.6f32; 8];
            match i {
                0..=2 => r[i] = 4.0,
                6..=8 => r[i - 3] = 4.0,
                _ => {}
            }
            rows.push(r);
        }
        let chat = Matrix::from_rows(&rows).unwrap();
        let sol = solve(&chat, &fixed(1, false)).unwrap();
        let want = [
            Some(0),
            Some(1),
            Some(2),
            None,
            None,
            None,
            Some(3),
            Some(4),
            Some(5),
        ];
        assert_eq!(route(&sol.hypotheses[0]), want);
    }

    #[test]
    fn solve_rejects_bad_input_with_precise_errors() {
        let chat = Matrix::from_rows(&[vec![1.0, f32::INFINITY]]).unwrap();
        let err = solve(&chat, &fixed(1, false)).unwrap_err();
        assert!(err.to_string().contains("row 0, column 1"), "{err}");
        let ok = Matrix::from_rows(&[vec![1.0, 2.0]]).unwrap();
        let err = solve(&ok, &fixed(0, false)).unwrap_err();
        assert!(err.to_string().contains("`flows`"), "{err}");
        let mut p = fixed(1, false);
        p.fan_out = MAX_FAN_OUT + 1;
        assert!(solve(&ok, &p).is_err());
        p = fixed(1, false);
        p.hidden_cost = HiddenCost::Fixed(-1.0);
        assert!(solve(&ok, &p).is_err());
        assert!(matches!(
            solve(&Matrix::zeros(0, 0), &fixed(1, false)),
            Err(Error::Empty(_))
        ));
    }
}
