//! `F > 1`, exact: the true min-cost flow of `F` units, by successive shortest paths with
//! Johnson potentials (Dijkstra on reduced costs) over the implicit residual graph.
//!
//! Every matching node is split into `x_in -> x_out` (capacity 1, cost `1/ĉ`); every other arc
//! is uncapacitated (the `F` units fit through hidden nodes). Arc costs: into `x_in` 0, into
//! `h` by a source or forward edge `W`, horizontal `h -> h` 0, into the sink 0. The residual
//! graph is never built: forward arcs are generated from the grid, and reverse arcs exist only
//! where flow runs, which is kept sparse (a bitset of used matching nodes, a bitset of hidden
//! nodes with flow, and a map node -> (predecessor, units)).
//!
//! The first unit is the DAG shortest path; its per-node distances are the initial potentials.
//! Each later unit runs Dijkstra from the source, stopping when the sink is settled; potentials
//! are then raised by `min(dist, dist(sink))`, which keeps every residual reduced cost >= 0.
//! The final flow is decomposed into `F` paths by walking back from the sink (at a node with
//! several incoming units the smallest node id is taken first) and ranked by increasing cost.
//!
//! Memory: per node (`3·Q·D` of them) an `f64` potential, an `f64` distance and a `u32`
//! predecessor, i.e. 60 bytes per cell (about 350 MB for 2400 x 2400), plus the heap.

use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap};

use super::graph::{hypothesis_from_steps, match_cost, Kind, Step};
use super::Hypothesis;
use crate::{Error, Matrix, Result};

const XIN: u32 = 0;
const XOUT: u32 = 1;
const HID: u32 = 2;
/// Flag on a predecessor entry: the arc used is the reverse of an original arc.
const REV: u32 = 1 << 31;
const NONE: u32 = u32::MAX;

/// Min-cost flow of `flows` units; hypotheses ranked by increasing cost.
/// Inputs must have been checked by the caller.
pub(crate) fn min_cost_flow(
    chat: &Matrix,
    fan_out: usize,
    horizontal: bool,
    w: f64,
    flows: usize,
) -> Result<Vec<Hypothesis>> {
    let cells = chat.rows() * chat.cols();
    if cells.checked_mul(3).is_none_or(|n| n + 2 >= REV as usize) {
        return Err(Error::Shape(format!(
            "the {}x{} similarity matrix is too large for the exact solver (at most {} cells)",
            chat.rows(),
            chat.cols(),
            (REV as usize - 2) / 3
        )));
    }
    let mut g = Residual::new(chat, fan_out, horizontal, w);
    let mut s = Search::new(3 * cells as u32 + 2);
    g.dag_potentials(&mut s);
    g.augment(&s);
    for _ in 1..flows {
        g.dijkstra(&mut s);
        s.raise_potentials(g.sink());
        g.augment(&s);
    }
    let mut hyps: Vec<Hypothesis> = g
        .decompose(flows)
        .iter()
        .map(|steps| hypothesis_from_steps(chat, w, steps, 0))
        .collect();
    hyps.sort_by(|a, b| a.cost.total_cmp(&b.cost));
    for (n, h) in hyps.iter_mut().enumerate() {
        h.rank = n + 1;
    }
    Ok(hyps)
}

/// Potentials, distances and predecessors of the shortest-path searches.
struct Search {
    pot: Vec<f64>,
    dist: Vec<f64>,
    pred: Vec<u32>,
    heap: BinaryHeap<Entry>,
}

impl Search {
    fn new(nodes: u32) -> Self {
        let n = nodes as usize;
        Search {
            pot: vec![0.0; n],
            dist: vec![f64::INFINITY; n],
            pred: vec![NONE; n],
            heap: BinaryHeap::new(),
        }
    }

    /// `pot += min(dist, dist(sink))`: keeps reduced costs non-negative after an early stop.
    fn raise_potentials(&mut self, sink: u32) {
        let dt = self.dist[sink as usize];
        for (p, &d) in self.pot.iter_mut().zip(&self.dist) {
            *p += d.min(dt);
        }
    }
}

/// Min-heap entry on distance.
#[derive(PartialEq)]
struct Entry(f64, u32);

impl Eq for Entry {}

impl Ord for Entry {
    fn cmp(&self, other: &Self) -> Ordering {
        other.0.total_cmp(&self.0).then(other.1.cmp(&self.1))
    }
}

impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// The graph with its current flow.
struct Residual<'a> {
    chat: &'a Matrix,
    q: usize,
    d: usize,
    k: usize,
    horizontal: bool,
    w: f64,
    /// Matching nodes whose split arc carries a unit.
    used: Vec<u64>,
    /// Hidden nodes with incoming flow.
    h_flow: Vec<u64>,
    /// Node -> (predecessor node, units) for `x_in`, `h` and the sink.
    flow_in: HashMap<u32, Vec<(u32, u32)>>,
}

fn bit(v: &[u64], n: usize) -> bool {
    v[n / 64] & (1 << (n % 64)) != 0
}

fn set_bit(v: &mut [u64], n: usize, on: bool) {
    if on {
        v[n / 64] |= 1 << (n % 64);
    } else {
        v[n / 64] &= !(1 << (n % 64));
    }
}

impl<'a> Residual<'a> {
    fn new(chat: &'a Matrix, k: usize, horizontal: bool, w: f64) -> Self {
        let cells = chat.rows() * chat.cols();
        Residual {
            chat,
            q: chat.rows(),
            d: chat.cols(),
            k,
            horizontal,
            w,
            used: vec![0; cells.div_ceil(64)],
            h_flow: vec![0; cells.div_ceil(64)],
            flow_in: HashMap::new(),
        }
    }

    fn source(&self) -> u32 {
        (3 * self.q * self.d) as u32
    }

    fn sink(&self) -> u32 {
        self.source() + 1
    }

    fn node(&self, i: usize, j: usize, t: u32) -> u32 {
        (3 * (i * self.d + j)) as u32 + t
    }

    fn x_cost(&self, cell: usize) -> f64 {
        match_cost(self.chat.as_slice()[cell])
    }

    /// Calls `f(v, cost, reverse)` for every residual arc out of `u`.
    #[inline]
    fn arcs(&self, u: u32, mut f: impl FnMut(u32, f64, bool)) {
        let (src, sink) = (self.source(), self.sink());
        if u == sink {
            return;
        }
        if u == src {
            for j in 0..self.d {
                f(self.node(0, j, XIN), 0.0, false);
                f(self.node(0, j, HID), self.w, false);
            }
            return;
        }
        let cell = (u / 3) as usize;
        let (i, j) = (cell / self.d, cell % self.d);
        let t = u % 3;
        if t == XIN {
            if bit(&self.used, cell) {
                for &(p, _) in &self.flow_in[&u] {
                    if p != src {
                        f(p, 0.0, true);
                    }
                }
            } else {
                let c = self.x_cost(cell);
                if c.is_finite() {
                    f(u + 1, c, false);
                }
            }
            return;
        }
        if i + 1 == self.q {
            f(sink, 0.0, false);
        } else {
            for kk in j..=(j + self.k).min(self.d - 1) {
                f(self.node(i + 1, kk, XIN), 0.0, false);
                f(self.node(i + 1, kk, HID), self.w, false);
            }
        }
        let right = self.horizontal && j + 1 < self.d;
        if t == XOUT {
            if right {
                f(u + 2, 0.0, false); // x_in of (i, j+1)
            }
            if bit(&self.used, cell) {
                f(u - 1, -self.x_cost(cell), true);
            }
        } else {
            if right {
                f(u + 3, 0.0, false);
            }
            if bit(&self.h_flow, cell) {
                for &(p, _) in &self.flow_in[&u] {
                    if p != src {
                        let c = if j > 0 && p == u - 3 { 0.0 } else { self.w };
                        f(p, -c, true);
                    }
                }
            }
        }
    }

    /// DAG shortest distances from the source (the initial potentials) and predecessors.
    fn dag_potentials(&self, s: &mut Search) {
        let (q, d, k, w) = (self.q, self.d, self.k, self.w);
        let (src, sink) = (self.source(), self.sink());
        s.pot[src as usize] = 0.0;
        let relax = |s: &mut Search, from: u32, to: u32, c: f64| {
            let nd = s.pot[from as usize] + c;
            if nd < s.pot[to as usize] {
                s.pot[to as usize] = nd;
                s.pred[to as usize] = from;
            }
        };
        s.pot.fill(f64::INFINITY);
        s.pot[src as usize] = 0.0;
        for i in 0..q {
            for j in 0..d {
                let (xin, xout, h) = (
                    self.node(i, j, XIN),
                    self.node(i, j, XOUT),
                    self.node(i, j, HID),
                );
                if i == 0 {
                    relax(s, src, xin, 0.0);
                    relax(s, src, h, w);
                } else {
                    for jj in j.saturating_sub(k)..=j {
                        for from in [self.node(i - 1, jj, XOUT), self.node(i - 1, jj, HID)] {
                            relax(s, from, xin, 0.0);
                            relax(s, from, h, w);
                        }
                    }
                }
                if self.horizontal && j > 0 {
                    relax(s, xout - 3, xin, 0.0);
                    relax(s, h - 3, h, 0.0);
                }
                let c = self.x_cost(i * d + j);
                if c.is_finite() {
                    relax(s, xin, xout, c);
                }
                if i + 1 == q {
                    relax(s, xout, sink, 0.0);
                    relax(s, h, sink, 0.0);
                }
            }
        }
        s.dist.copy_from_slice(&s.pot);
    }

    /// Dijkstra on reduced costs from the source until the sink is settled.
    fn dijkstra(&self, s: &mut Search) {
        let (src, sink) = (self.source(), self.sink());
        s.dist.fill(f64::INFINITY);
        s.heap.clear();
        s.dist[src as usize] = 0.0;
        s.heap.push(Entry(0.0, src));
        while let Some(Entry(du, u)) = s.heap.pop() {
            if du > s.dist[u as usize] {
                continue;
            }
            if u == sink {
                break;
            }
            let pu = s.pot[u as usize];
            let Search {
                pot,
                dist,
                pred,
                heap,
            } = s;
            self.arcs(u, |v, c, rev| {
                let r = (c + pu - pot[v as usize]).max(0.0);
                let nd = du + r;
                if nd < dist[v as usize] {
                    dist[v as usize] = nd;
                    pred[v as usize] = if rev { u | REV } else { u };
                    heap.push(Entry(nd, v));
                }
            });
        }
        debug_assert!(
            s.dist[sink as usize].is_finite(),
            "hidden paths always reach the sink"
        );
    }

    /// Pushes one unit along the predecessor chain from the sink.
    fn augment(&mut self, s: &Search) {
        let src = self.source();
        let mut v = self.sink();
        while v != src {
            let p = s.pred[v as usize];
            let (u, rev) = (p & !REV, p & REV != 0);
            if rev {
                self.unpush(v, u);
            } else {
                self.push(u, v);
            }
            v = u;
        }
    }

    /// One more unit on the original arc `u -> v`.
    fn push(&mut self, u: u32, v: u32) {
        if v < self.source() && v % 3 == XOUT {
            set_bit(&mut self.used, (v / 3) as usize, true);
            return;
        }
        if v < self.source() && v % 3 == HID {
            set_bit(&mut self.h_flow, (v / 3) as usize, true);
        }
        let list = self.flow_in.entry(v).or_default();
        match list.iter_mut().find(|e| e.0 == u) {
            Some(e) => e.1 += 1,
            None => list.push((u, 1)),
        }
    }

    /// One unit less on the original arc `u -> v`.
    fn unpush(&mut self, u: u32, v: u32) {
        if v < self.source() && v % 3 == XOUT {
            set_bit(&mut self.used, (v / 3) as usize, false);
            return;
        }
        let list = self
            .flow_in
            .get_mut(&v)
            .expect("a reverse arc exists only where flow runs");
        let n = list
            .iter()
            .position(|e| e.0 == u)
            .expect("a reverse arc exists only where flow runs");
        list[n].1 -= 1;
        if list[n].1 == 0 {
            list.swap_remove(n);
        }
        if list.is_empty() {
            self.flow_in.remove(&v);
            if v < self.source() && v % 3 == HID {
                set_bit(&mut self.h_flow, (v / 3) as usize, false);
            }
        }
    }

    /// Splits the flow into `flows` source-sink paths (node steps in visiting order).
    fn decompose(&mut self, flows: usize) -> Vec<Vec<Step>> {
        let src = self.source();
        let mut paths = Vec::with_capacity(flows);
        for _ in 0..flows {
            let mut steps = Vec::new();
            let mut v = self.sink();
            loop {
                let list = self
                    .flow_in
                    .get(&v)
                    .expect("flow conservation: every node with outflow has inflow");
                let p = list.iter().map(|e| e.0).min().expect("non-empty list");
                self.unpush(p, v);
                if p == src {
                    break;
                }
                let cell = (p / 3) as usize;
                let (row, col) = (cell / self.d, cell % self.d);
                let kind = if p % 3 == XOUT {
                    Kind::Match
                } else {
                    Kind::Hidden
                };
                steps.push(Step { row, col, kind });
                // From x_out the unit came through the split arc from x_in.
                v = if kind == Kind::Match { p - 1 } else { p };
            }
            steps.reverse();
            paths.push(steps);
        }
        paths
    }
}

#[cfg(test)]
mod tests {
    use super::super::greedy::greedy_paths;
    use super::super::reference::{check_valid, generic_min_cost_flow, random_instance};
    use super::super::shortest_path;
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn exact_beats_greedy_on_a_crossing() {
        // Greedy takes the diagonal (cost 0.2 + 0.2 + 0.2), leaving the second flow with the
        // poor nodes; the optimum of 2 flows uses two parallel routes instead.
        let chat = Matrix::from_rows(&[
            vec![5.0, 4.0, 0.1],
            vec![0.1, 5.0, 4.0],
            vec![0.1, 4.0, 5.0],
        ])
        .unwrap();
        let exact = min_cost_flow(&chat, 1, false, 10.0, 2).unwrap();
        let greedy = greedy_paths(&chat, 1, false, 10.0, 2, None);
        let te: f64 = exact.iter().map(|h| h.cost).sum();
        let tg: f64 = greedy.iter().map(|h| h.cost).sum();
        let opt = generic_min_cost_flow(&chat, 1, false, 10.0, 2).unwrap();
        assert!((te - opt).abs() < 1e-9, "{te} vs {opt}");
        assert!(
            tg > te + 1e-6,
            "greedy {tg} should be worse than exact {te} here"
        );
        assert!(exact[0].cost <= exact[1].cost);
        assert_eq!((exact[0].rank, exact[1].rank), (1, 2));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        #[test]
        fn exact_equals_generic_min_cost_flow(
            (chat, k, horizontal, w) in random_instance(),
            flows in 1usize..=3,
        ) {
            let hyps = min_cost_flow(&chat, k, horizontal, w, flows).unwrap();
            prop_assert_eq!(hyps.len(), flows);
            let mut seen = std::collections::HashSet::new();
            for h in &hyps {
                check_valid(h, &chat, k, horizontal, w, None);
                for r in &h.rows {
                    for m in &r.matches {
                        prop_assert!(seen.insert((r.query, m.reference)), "matching node reused");
                    }
                }
            }
            prop_assert!(hyps.windows(2).all(|p| p[0].cost <= p[1].cost));
            let total: f64 = hyps.iter().map(|h| h.cost).sum();
            let opt = generic_min_cost_flow(&chat, k, horizontal, w, flows).unwrap();
            prop_assert!((total - opt).abs() <= 1e-9 * opt.max(1.0), "exact {total} vs optimum {opt}");
            if flows == 1 {
                let sp = shortest_path(&chat, k, horizontal, w, None).unwrap();
                prop_assert!((sp.cost - total).abs() <= 1e-9 * total.max(1.0));
            }
        }
    }
}
