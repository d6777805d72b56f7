//! Min-marginals along a hypothesis over the whole graph: for every query row, the cheapest
//! complete path that matches *near* the hypothesis, *elsewhere*, or goes *hidden*. A library
//! function (benched in `benches/solver.rs`, `row_alternatives_k4`); the shipped confidences
//! read local forms of the same quantity instead (the box window, the discounted passes of
//! `confidence/discounted.rs`, which are these recurrences with each row scaled by `g`).
//!
//! With `F_i` the forward DP of [`super::shortest_path()`] (cheapest source path ending at a node,
//! node included) and `B_i` a backward DP (cheapest continuation from a node to the sink, node
//! excluded), the cheapest complete path through a node costs `F + B`. The backward rows are
//! `G[k] = min(c_{i+1,k} + BX_{i+1}[k], W + BH_{i+1}[k])`, `base_j = min_{k in [j, j+K]} G[k]`
//! (0 in the last row: the sink), `BX[j] = min(base_j, c_{i,j+1} + BX[j+1])`,
//! `BH[j] = min(base_j, BH[j+1])` (second terms with horizontal edges only).
//!
//! Memory is `O(sqrt(Q)·D)`: a backward pass keeps every `s`-th backward row (`s = ceil(sqrt Q)`)
//! as a checkpoint; the forward pass then recomputes the backward rows of one block of `s` rows
//! at a time from the next checkpoint. Time: two backward passes and one forward pass.

use super::graph::{check_inputs, Blocked};
use super::kernel::row_costs;
use super::shortest_path::{Dp, RowState, Scratch};
use super::Hypothesis;
use crate::window::leading_min_in_place;
use crate::{Error, Matrix, Result};

/// The min-marginals of one query row.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RowAlternatives {
    /// Query (row) index `i`.
    pub query: usize,
    /// The column window `[a, b]` (inclusive): the hypothesis's matched columns in this row
    /// widened by `radius` and clamped to the matrix. For a hidden row, the matched columns of
    /// the nearest matched row (the earlier one on a tie). `None` when the hypothesis matches
    /// nothing at all.
    pub window: Option<(usize, usize)>,
    /// Cheapest complete path through a matching node `x_ij` with `j` in the window
    /// (`+inf` when there is none).
    pub inside: f64,
    /// Cheapest complete path through a matching node `x_ij` with `j` outside the window
    /// (`+inf` when there is none).
    pub outside: f64,
    /// Cheapest complete path through a hidden node of this row.
    pub hidden: f64,
}

/// Min-marginals of every query row around `path` (see [`RowAlternatives`]).
///
/// Uses the same graph as [`super::shortest_path()`] with the same arguments; `path` must have one
/// row per query row and columns inside the matrix. Time `O(Q·D)`, memory `O(sqrt(Q)·D)`.
pub fn row_alternatives(
    chat: &Matrix,
    fan_out: usize,
    horizontal: bool,
    w: f64,
    blocked: Option<&Blocked>,
    path: &Hypothesis,
    radius: usize,
) -> Result<Vec<RowAlternatives>> {
    check_inputs(chat, fan_out, w, blocked)?;
    let windows = windows(chat, path, radius)?;
    let (q, d) = (chat.rows(), chat.cols());
    let dp = Dp::new(chat, fan_out, horizontal, w, blocked);
    let back = Backward {
        blocked,
        chat,
        k: fan_out,
        horizontal,
        w,
    };
    let s = (q as f64).sqrt().ceil().max(1.0) as usize;
    // Backward pass: checkpoints at rows 0, s, 2s, ...
    let mut next = BackRow::new(d);
    let mut cur = BackRow::new(d);
    let mut scratch = BackScratch::new(d);
    let mut checkpoints = vec![BackRow::new(d); q.div_ceil(s)];
    for i in (0..q).rev() {
        back.step(i, (i + 1 < q).then_some(&next), &mut cur, &mut scratch);
        if i % s == 0 {
            checkpoints[i / s].clone_from(&cur);
        }
        std::mem::swap(&mut next, &mut cur);
    }
    // Forward pass, one block of s rows at a time.
    let mut out = Vec::with_capacity(q);
    let mut block: Vec<BackRow> = vec![BackRow::new(d); s];
    let mut fprev = RowState::new(d);
    let mut fcur = RowState::new(d);
    let mut forward_scratch = Scratch::default();
    for b0 in (0..q).step_by(s) {
        let b1 = (b0 + s).min(q);
        // Backward rows b1-1 ..= b0 from the checkpoint of row b1 (or the sink).
        for i in (b0..b1).rev() {
            let n = i - b0;
            let (lo, hi) = block.split_at_mut(n + 1);
            let next_row = if i + 1 == q {
                None
            } else if i + 1 == b1 {
                Some(&checkpoints[b1 / s])
            } else {
                Some(&hi[0])
            };
            back.step(i, next_row, &mut lo[n], &mut scratch);
        }
        for i in b0..b1 {
            dp.values_step(
                i,
                (i > 0).then_some(&fprev),
                &mut fcur,
                &mut forward_scratch,
            );
            out.push(combine(i, &fcur, &block[i - b0], windows[i]));
            std::mem::swap(&mut fprev, &mut fcur);
        }
    }
    Ok(out)
}

/// Backward DP values of one row: cheapest continuation to the sink, node cost excluded.
#[derive(Clone, Debug)]
struct BackRow {
    x: Vec<f64>,
    h: Vec<f64>,
}

impl BackRow {
    fn new(d: usize) -> Self {
        BackRow {
            x: vec![0.0; d],
            h: vec![0.0; d],
        }
    }
}

struct Backward<'a> {
    blocked: Option<&'a Blocked>,
    chat: &'a Matrix,
    k: usize,
    horizontal: bool,
    w: f64,
}

impl Backward<'_> {
    /// Row `i` from row `i+1` (`None` for the last row). `g`, `cost`, `tmp`: scratch of `D`.
    fn step(&self, i: usize, next: Option<&BackRow>, cur: &mut BackRow, s: &mut BackScratch) {
        let BackScratch { g, cost, tmp } = s;
        let blocked = |row: usize| self.blocked.map(|b| (b, row, 0));
        match next {
            None => g.fill(0.0),
            Some(n) => {
                row_costs(self.chat.row(i + 1), blocked(i + 1), cost);
                for (((gk, &c), &x), &h) in g.iter_mut().zip(cost.iter()).zip(&n.x).zip(&n.h) {
                    *gk = (c + x).min(self.w + h);
                }
                leading_min_in_place(g, self.k, tmp);
            }
        }
        if !self.horizontal {
            cur.x.copy_from_slice(g);
            cur.h.copy_from_slice(g);
            return;
        }
        row_costs(self.chat.row(i), blocked(i), cost);
        let mut right_x = f64::INFINITY; // c_{i,j+1} + BX[j+1]
        let mut right_h = f64::INFINITY;
        let cells = g
            .iter()
            .zip(cost.iter())
            .zip(cur.x.iter_mut().zip(cur.h.iter_mut()));
        for ((&gj, &c), (cx, ch)) in cells.rev() {
            let bx = gj.min(right_x);
            let bh = gj.min(right_h);
            *cx = bx;
            *ch = bh;
            right_x = c + bx;
            right_h = bh;
        }
    }
}

/// Scratch rows of [`Backward::step`].
struct BackScratch {
    g: Vec<f64>,
    cost: Vec<f64>,
    tmp: Vec<f64>,
}

impl BackScratch {
    fn new(d: usize) -> Self {
        BackScratch {
            g: vec![0.0; d],
            cost: vec![0.0; d],
            tmp: vec![0.0; d],
        }
    }
}

fn combine(i: usize, f: &RowState, b: &BackRow, window: Option<(usize, usize)>) -> RowAlternatives {
    let mut inside = f64::INFINITY;
    let mut outside = f64::INFINITY;
    let mut hidden = f64::INFINITY;
    let through = f.x.iter().zip(&b.x).zip(f.h.iter().zip(&b.h));
    for (j, ((fx, bx), (fh, bh))) in through.enumerate() {
        let through_x = fx + bx;
        if window.is_some_and(|(a, z)| (a..=z).contains(&j)) {
            inside = inside.min(through_x);
        } else {
            outside = outside.min(through_x);
        }
        hidden = hidden.min(fh + bh);
    }
    RowAlternatives {
        query: i,
        window,
        inside,
        outside,
        hidden,
    }
}

/// The column window of every row (see [`RowAlternatives::window`]).
fn windows(chat: &Matrix, path: &Hypothesis, radius: usize) -> Result<Vec<Option<(usize, usize)>>> {
    let (q, d) = (chat.rows(), chat.cols());
    if path.rows.len() != q {
        return Err(Error::Shape(format!(
            "the hypothesis has {} rows but the similarity matrix has {q}",
            path.rows.len()
        )));
    }
    let mut own: Vec<Option<(usize, usize)>> = Vec::with_capacity(q);
    for (i, r) in path.rows.iter().enumerate() {
        if let Some(m) = r.matches.iter().find(|m| m.reference >= d) {
            return Err(Error::Shape(format!(
                "row {i} of the hypothesis matches reference {} but the matrix has {d} columns",
                m.reference
            )));
        }
        let lo = r.matches.iter().map(|m| m.reference).min();
        let hi = r.matches.iter().map(|m| m.reference).max();
        own.push(lo.zip(hi));
    }
    // Nearest matched row for hidden rows: scan from both sides.
    let mut last = None;
    let before: Vec<Option<(usize, (usize, usize))>> = own
        .iter()
        .enumerate()
        .map(|(i, c)| {
            if let Some(c) = c {
                last = Some((i, *c));
            }
            last
        })
        .collect();
    let mut after = None;
    let mut out = vec![None; q];
    for (i, (c, b)) in own.iter().zip(&before).enumerate().rev() {
        if let Some(c) = c {
            after = Some((i, *c));
        }
        let cols = match (*b, after) {
            (Some((a, ca)), Some((b, cb))) => Some(if i - a <= b - i { ca } else { cb }),
            (Some((_, c)), None) | (None, Some((_, c))) => Some(c),
            (None, None) => None,
        };
        out[i] = cols.map(|(lo, hi)| (lo.saturating_sub(radius), (hi + radius).min(d - 1)));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::super::graph::Kind;
    use super::super::reference::{check_valid, for_each_path, random_instance};
    use super::super::shortest_path;
    use super::*;
    use proptest::prelude::*;

    fn brute(
        chat: &Matrix,
        k: usize,
        horizontal: bool,
        w: f64,
        blocked: Option<&Blocked>,
        win: &[Option<(usize, usize)>],
    ) -> Vec<(f64, f64, f64)> {
        let mut best = vec![(f64::INFINITY, f64::INFINITY, f64::INFINITY); chat.rows()];
        for_each_path(chat, k, horizontal, w, blocked, &mut |steps, cost| {
            for s in steps {
                let b = &mut best[s.row];
                match s.kind {
                    Kind::Hidden => b.2 = b.2.min(cost),
                    Kind::Match => {
                        if win[s.row].is_some_and(|(a, z)| (a..=z).contains(&s.col)) {
                            b.0 = b.0.min(cost);
                        } else {
                            b.1 = b.1.min(cost);
                        }
                    }
                }
            }
        });
        best
    }

    fn close(a: f64, b: f64) -> bool {
        a == b || (a - b).abs() <= 1e-9 * a.abs().max(1.0)
    }

    #[test]
    fn hidden_rows_take_the_nearest_matched_window() {
        let chat = Matrix::from_rows(&[
            vec![5.0, 0.1, 0.1, 0.1, 0.1],
            vec![0.1, 0.1, 0.1, 0.1, 0.1],
            vec![0.1, 0.1, 0.1, 0.1, 0.1],
            vec![0.1, 0.1, 0.1, 0.1, 5.0],
        ])
        .unwrap();
        let h = shortest_path(&chat, 2, true, 1.0, None).unwrap();
        let w = windows(&chat, &h, 1).unwrap();
        assert_eq!(
            w,
            vec![Some((0, 1)), Some((0, 1)), Some((3, 4)), Some((3, 4))]
        );
        let alts = row_alternatives(&chat, 2, true, 1.0, None, &h, 1).unwrap();
        // The best path goes through the window of every matched row.
        assert!(close(alts[0].inside, h.cost) && close(alts[3].inside, h.cost));
        assert!(
            alts[0].outside > h.cost && close(alts[1].hidden, h.cost),
            "{alts:?} {h:?}"
        );
    }

    #[test]
    fn rejects_a_hypothesis_of_another_shape() {
        let chat = Matrix::from_rows(&[vec![1.0, 2.0]]).unwrap();
        let h = shortest_path(&chat, 1, true, 1.0, None).unwrap();
        let other = Matrix::from_rows(&[vec![1.0, 2.0], vec![1.0, 2.0]]).unwrap();
        let err = row_alternatives(&other, 1, true, 1.0, None, &h, 0).unwrap_err();
        assert!(err.to_string().contains("1 rows"), "{err}");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(150))]
        #[test]
        fn equals_brute_force(
            (chat, k, horizontal, w) in random_instance(),
            radius in 0usize..3,
            block_seed in any::<u64>(),
        ) {
            let mut blocked = Blocked::new(chat.rows(), chat.cols());
            for i in 0..chat.rows() {
                for j in 0..chat.cols() {
                    if (block_seed >> ((i * 7 + j) % 64)) & 1 == 1 && (i + j) % 3 == 0 {
                        blocked.block(i, j);
                    }
                }
            }
            let b = Some(&blocked);
            let h = shortest_path(&chat, k, horizontal, w, b).unwrap();
            check_valid(&h, &chat, k, horizontal, w, b);
            let alts = row_alternatives(&chat, k, horizontal, w, b, &h, radius).unwrap();
            let win = windows(&chat, &h, radius).unwrap();
            let want = brute(&chat, k, horizontal, w, b, &win);
            for (a, (inside, outside, hidden)) in alts.iter().zip(want) {
                prop_assert!(close(a.inside, inside), "row {} inside {} vs {}", a.query, a.inside, inside);
                prop_assert!(close(a.outside, outside), "row {} outside {} vs {}", a.query, a.outside, outside);
                prop_assert!(close(a.hidden, hidden), "row {} hidden {} vs {}", a.query, a.hidden, hidden);
            }
        }
    }
}
