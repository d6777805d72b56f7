//! Test-only reference solvers, written plainly so they are easy to trust:
//!
//! * [`for_each_path`]: brute-force enumeration of every source-sink path (tiny instances);
//! * [`generic_min_cost_flow`]: min-cost flow on the explicit graph (matching nodes split into
//!   `in -> out` with capacity 1), successive shortest paths with Bellman-Ford;
//! * [`check_valid`]: checks that a hypothesis is a path of the graph and its cost is right;
//! * [`random_instance`]: the proptest strategy for small random instances.

use super::graph::{match_cost, Blocked, Kind, Step};
use super::Hypothesis;
use crate::Matrix;
use proptest::prelude::*;

/// Small random instances: `Q <= 6`, `D <= 8`, `ĉ` in `[-0.2, 3]`, `K` in `0..=3`, horizontal
/// on/off, `W` in `(0.2, 3)`.
pub(crate) fn random_instance() -> impl Strategy<Value = (Matrix, usize, bool, f64)> {
    (1usize..=6, 1usize..=8)
        .prop_flat_map(|(q, d)| {
            (
                prop::collection::vec(-0.2f32..3.0, q * d),
                Just((q, d)),
                0usize..=3,
                any::<bool>(),
                0.2f64..3.0,
            )
        })
        .prop_map(|(v, (q, d), k, hz, w)| {
            (Matrix::from_vec(q, d, v).expect("q*d values"), k, hz, w)
        })
}

fn usable(chat: &Matrix, blocked: Option<&Blocked>, i: usize, j: usize) -> bool {
    chat.get(i, j) > 0.0 && !blocked.is_some_and(|b| b.is_blocked(i, j))
}

/// Calls `f(path, cost)` for every source-sink path.
pub(crate) fn for_each_path(
    chat: &Matrix,
    k: usize,
    horizontal: bool,
    w: f64,
    blocked: Option<&Blocked>,
    f: &mut dyn FnMut(&[Step], f64),
) {
    struct Ctx<'a> {
        chat: &'a Matrix,
        k: usize,
        horizontal: bool,
        w: f64,
        blocked: Option<&'a Blocked>,
    }
    fn dfs(c: &Ctx, path: &mut Vec<Step>, cost: f64, f: &mut dyn FnMut(&[Step], f64)) {
        let s = *path.last().expect("non-empty path");
        let (q, d) = (c.chat.rows(), c.chat.cols());
        if s.row == q - 1 {
            f(path, cost);
        }
        let mut visit = |path: &mut Vec<Step>, step: Step, add: f64| {
            path.push(step);
            dfs(c, path, cost + add, f);
            path.pop();
        };
        if c.horizontal && s.col + 1 < d {
            let next = Step {
                col: s.col + 1,
                ..s
            };
            match s.kind {
                Kind::Hidden => visit(path, next, 0.0),
                Kind::Match => {
                    if usable(c.chat, c.blocked, s.row, s.col + 1) {
                        visit(path, next, match_cost(c.chat.get(s.row, s.col + 1)));
                    }
                }
            }
        }
        if s.row + 1 < q {
            let i = s.row + 1;
            for kk in s.col..=(s.col + c.k).min(d - 1) {
                if usable(c.chat, c.blocked, i, kk) {
                    let step = Step {
                        row: i,
                        col: kk,
                        kind: Kind::Match,
                    };
                    visit(path, step, match_cost(c.chat.get(i, kk)));
                }
                let step = Step {
                    row: i,
                    col: kk,
                    kind: Kind::Hidden,
                };
                visit(path, step, c.w);
            }
        }
    }
    let ctx = Ctx {
        chat,
        k,
        horizontal,
        w,
        blocked,
    };
    let mut path = Vec::new();
    for j in 0..chat.cols() {
        if usable(chat, blocked, 0, j) {
            path.push(Step {
                row: 0,
                col: j,
                kind: Kind::Match,
            });
            dfs(&ctx, &mut path, match_cost(chat.get(0, j)), f);
            path.pop();
        }
        path.push(Step {
            row: 0,
            col: j,
            kind: Kind::Hidden,
        });
        dfs(&ctx, &mut path, w, f);
        path.pop();
    }
}

/// The cheapest path cost by enumeration.
pub(crate) fn brute_force_best(
    chat: &Matrix,
    k: usize,
    horizontal: bool,
    w: f64,
    blocked: Option<&Blocked>,
) -> f64 {
    let mut best = f64::INFINITY;
    for_each_path(chat, k, horizontal, w, blocked, &mut |_, c| {
        best = best.min(c)
    });
    best
}

/// Asserts that `h` is a valid path of the graph with the right cost.
pub(crate) fn check_valid(
    h: &Hypothesis,
    chat: &Matrix,
    k: usize,
    horizontal: bool,
    w: f64,
    blocked: Option<&Blocked>,
) {
    assert_eq!(h.rows.len(), chat.rows());
    let mut cost = 0.0;
    let mut last: Option<(usize, usize)> = None; // (row, last column) of the last matched row
    for (i, r) in h.rows.iter().enumerate() {
        assert_eq!(r.query, i);
        if r.matches.is_empty() {
            cost += w;
            continue;
        }
        if !horizontal {
            assert_eq!(
                r.matches.len(),
                1,
                "row {i}: several matches without horizontal edges"
            );
        }
        for (n, m) in r.matches.iter().enumerate() {
            assert!(
                usable(chat, blocked, i, m.reference),
                "row {i} uses unusable {m:?}"
            );
            assert_eq!(m.similarity, chat.get(i, m.reference));
            if n > 0 {
                assert_eq!(
                    m.reference,
                    r.matches[n - 1].reference + 1,
                    "row {i} not a run"
                );
            }
            cost += match_cost(m.similarity);
        }
        let first = r.matches[0].reference;
        if let Some((a, la)) = last {
            let gap = i - a - 1;
            assert!(first >= la, "row {i} goes backwards");
            if gap == 0 || !horizontal {
                assert!(first <= la + k * (gap + 1), "row {i} jumps too far");
            }
        }
        last = Some((i, r.matches[r.matches.len() - 1].reference));
    }
    assert!(
        (h.cost - cost).abs() <= 1e-9 * cost.max(1.0),
        "reported cost {} != node cost sum {cost}",
        h.cost
    );
}

/// Min-cost flow of `flows` units on the explicit graph; `None` if infeasible.
pub(crate) fn generic_min_cost_flow(
    chat: &Matrix,
    k: usize,
    horizontal: bool,
    w: f64,
    flows: usize,
) -> Option<f64> {
    let (q, d) = (chat.rows(), chat.cols());
    let (s, t) = (0, 1);
    let xin = |i: usize, j: usize| 2 + 3 * (i * d + j);
    let xout = |i: usize, j: usize| 3 + 3 * (i * d + j);
    let hid = |i: usize, j: usize| 4 + 3 * (i * d + j);
    let n = 2 + 3 * q * d;
    // Edge list with paired reverse edges: (to, cap, cost).
    let mut to = Vec::new();
    let mut cap: Vec<i64> = Vec::new();
    let mut cost = Vec::new();
    let mut adj: Vec<Vec<usize>> = vec![Vec::new(); n];
    let big = flows as i64;
    let mut add = |u: usize, v: usize, c: i64, w: f64| {
        adj[u].push(to.len());
        to.push(v);
        cap.push(c);
        cost.push(w);
        adj[v].push(to.len());
        to.push(u);
        cap.push(0);
        cost.push(-w);
    };
    for j in 0..d {
        add(s, xin(0, j), big, 0.0);
        add(s, hid(0, j), big, w);
    }
    for i in 0..q {
        for j in 0..d {
            if chat.get(i, j) > 0.0 {
                add(xin(i, j), xout(i, j), 1, match_cost(chat.get(i, j)));
            }
            for from in [xout(i, j), hid(i, j)] {
                if i + 1 == q {
                    add(from, t, big, 0.0);
                } else {
                    for kk in j..=(j + k).min(d - 1) {
                        add(from, xin(i + 1, kk), big, 0.0);
                        add(from, hid(i + 1, kk), big, w);
                    }
                }
            }
            if horizontal && j + 1 < d {
                add(xout(i, j), xin(i, j + 1), big, 0.0);
                add(hid(i, j), hid(i, j + 1), big, 0.0);
            }
        }
    }
    let mut total = 0.0;
    for _ in 0..flows {
        // Bellman-Ford from the source over edges with residual capacity.
        let mut dist = vec![f64::INFINITY; n];
        let mut pred: Vec<Option<usize>> = vec![None; n];
        dist[s] = 0.0;
        for _ in 0..n {
            let mut changed = false;
            for (u, edges) in adj.iter().enumerate() {
                if dist[u].is_infinite() {
                    continue;
                }
                for &e in edges {
                    if cap[e] > 0 && dist[u] + cost[e] < dist[to[e]] - 1e-12 {
                        dist[to[e]] = dist[u] + cost[e];
                        pred[to[e]] = Some(e);
                        changed = true;
                    }
                }
            }
            if !changed {
                break;
            }
        }
        if dist[t].is_infinite() {
            return None;
        }
        let mut v = t;
        while let Some(e) = pred[v] {
            cap[e] -= 1;
            cap[e ^ 1] += 1;
            total += cost[e];
            v = to[e ^ 1];
        }
    }
    Some(total)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn brute_force_counts_paths_of_a_tiny_graph() {
        // 2x2, K = 1, no horizontal edges: 4 first nodes, each with 4 successors.
        let chat = Matrix::from_rows(&[vec![1.0, 1.0], vec![1.0, 1.0]]).unwrap();
        let mut n = 0;
        for_each_path(&chat, 1, false, 1.0, None, &mut |_, _| n += 1);
        // Column 0 reaches 2 columns x 2 kinds, column 1 reaches 1 column x 2 kinds.
        assert_eq!(n, 2 * 4 + 2 * 2);
        assert_eq!(brute_force_best(&chat, 1, false, 1.0, None), 2.0);
    }

    #[test]
    fn generic_flow_pays_for_disjoint_matches() {
        // Two flows on a 1x2 matrix: both matches (costs 1 and 2), or one match and hidden.
        let chat = Matrix::from_rows(&[vec![1.0, 0.5]]).unwrap();
        assert_eq!(generic_min_cost_flow(&chat, 0, false, 10.0, 2), Some(3.0));
        assert_eq!(generic_min_cost_flow(&chat, 0, false, 1.5, 2), Some(2.5));
    }
}
