//! `F > 1`, greedy (the flow paper's method): repeat the shortest path `F` times, each time
//! making the matching nodes already used unusable, and rank the paths in the order found.
//!
//! Each round is one `O(Q·D)` dynamic programme ([`super::shortest_path()`]); hidden nodes stay
//! available to every round, so every round finds a path. The total cost can only be higher
//! than or equal to the exact min-cost flow's. Inputs must have been checked by the caller.

use super::graph::{hypothesis_from_steps, Blocked};
use super::shortest_path::Dp;
use super::Hypothesis;
use crate::Matrix;

/// Up to `flows` greedy hypotheses, rank 1 first. With `stop = Some(f)` the search ends before
/// the first hypothesis of rank > 1 whose hidden fraction exceeds `f` (it is not returned).
pub(crate) fn greedy_paths(
    chat: &Matrix,
    fan_out: usize,
    horizontal: bool,
    w: f64,
    flows: usize,
    stop: Option<f64>,
) -> Vec<Hypothesis> {
    let mut blocked = Blocked::new(chat.rows(), chat.cols());
    let mut out = Vec::with_capacity(flows);
    for rank in 1..=flows {
        let b = (rank > 1).then_some(&blocked);
        let steps = Dp::new(chat, fan_out, horizontal, w, b).shortest_steps();
        let h = hypothesis_from_steps(chat, w, &steps, rank);
        if rank > 1 && stop.is_some_and(|f| h.hidden_fraction() > f) {
            break;
        }
        if rank < flows {
            blocked.block_hypothesis(&h);
        }
        out.push(h);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::super::reference::{check_valid, generic_min_cost_flow, random_instance};
    use super::super::{solve, HiddenCost, SolverParams};
    use super::*;
    use proptest::prelude::*;

    fn params(flows: usize, exact: bool) -> SolverParams {
        SolverParams {
            fan_out: 2,
            hidden_cost: HiddenCost::Fixed(2.0),
            flows,
            exact,
            horizontal: true,
            stop_hidden_fraction: None,
        }
    }

    /// A query route that drives the reference route twice (a loop): rows `0..6` see the
    /// places of columns `0..6` (strongly), rows `6..11` see columns `0..5` again (a bit weaker).
    fn loop_matrix() -> Matrix {
        let mut rows = Vec::new();
        for i in 0..11 {
            let mut r = vec![0.3f32; 6];
            r[i % 6] = if i < 6 { 5.0 } else { 4.0 };
            rows.push(r);
        }
        Matrix::from_rows(&rows).unwrap()
    }

    fn matched(h: &Hypothesis) -> Vec<Option<usize>> {
        h.rows
            .iter()
            .map(|r| r.matches.first().map(|m| m.reference))
            .collect()
    }

    #[test]
    fn second_flow_recovers_the_second_traversal() {
        // A monotone path cannot take both traversals: the first flow takes the stronger one
        // and goes hidden, the second flow is hidden first and then takes the other.
        let chat = loop_matrix();
        let first: Vec<_> = (0..11).map(|i| (i < 6).then_some(i)).collect();
        let second: Vec<_> = (0..11).map(|i| (i >= 6).then(|| i - 6)).collect();
        for exact in [false, true] {
            let sol = solve(&chat, &params(2, exact)).unwrap();
            assert_eq!(sol.hypotheses.len(), 2);
            assert_eq!(matched(&sol.hypotheses[0]), first, "exact={exact}");
            assert_eq!(matched(&sol.hypotheses[1]), second, "exact={exact}");
            let single = solve(&chat, &params(1, exact)).unwrap();
            assert_eq!(matched(&single.hypotheses[0]), first);
        }
    }

    #[test]
    fn greedy_never_reuses_a_matching_node() {
        let chat = loop_matrix();
        let hyps = greedy_paths(&chat, 3, true, 1.5, 4, None);
        let mut seen = std::collections::HashSet::new();
        for h in &hyps {
            for r in &h.rows {
                for m in &r.matches {
                    assert!(
                        seen.insert((r.query, m.reference)),
                        "reused {:?}",
                        (r.query, m)
                    );
                }
            }
        }
        assert_eq!(
            hyps.iter().map(|h| h.rank).collect::<Vec<_>>(),
            vec![1, 2, 3, 4]
        );
    }

    #[test]
    fn stopping_rule_drops_mostly_hidden_later_paths() {
        let chat = loop_matrix();
        let mut p = params(4, false);
        p.stop_hidden_fraction = Some(0.5);
        let sol = solve(&chat, &p).unwrap();
        assert!(!sol.hypotheses.is_empty());
        let all = solve(&chat, &params(4, false)).unwrap();
        let cut = all
            .hypotheses
            .iter()
            .skip(1)
            .position(|h| h.hidden_fraction() > 0.5);
        assert_eq!(sol.hypotheses.len(), cut.map_or(4, |c| c + 1));
        assert!(
            sol.hypotheses.len() < 4,
            "the test matrix must trigger the rule"
        );
        // The first path is kept even when it is mostly hidden.
        let dark = Matrix::from_rows(&vec![vec![0.1f32; 3]; 3]).unwrap();
        let mut p = params(3, false);
        p.stop_hidden_fraction = Some(0.0);
        let sol = solve(&dark, &p).unwrap();
        assert_eq!(sol.hypotheses.len(), 1);
        assert_eq!(sol.hypotheses[0].hidden_fraction(), 1.0);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(100))]
        #[test]
        fn greedy_is_valid_and_not_below_the_optimum(
            (chat, k, horizontal, w) in random_instance(),
            flows in 2usize..=3,
        ) {
            let hyps = greedy_paths(&chat, k, horizontal, w, flows, None);
            prop_assert_eq!(hyps.len(), flows);
            let mut blocked = Blocked::new(chat.rows(), chat.cols());
            for h in &hyps {
                check_valid(h, &chat, k, horizontal, w, Some(&blocked));
                blocked.block_hypothesis(h);
            }
            let total: f64 = hyps.iter().map(|h| h.cost).sum();
            let opt = generic_min_cost_flow(&chat, k, horizontal, w, flows).unwrap();
            prop_assert!(total >= opt - 1e-9 * opt.max(1.0), "greedy {total} < optimum {opt}");
        }
    }
}
