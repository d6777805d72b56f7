//! Sequence matching (Section II-F): SeqSLAM's idea of matching a window of consecutive queries
//! to a path of locations, with the path allowed to take any forward-only shape, so the query
//! drive may accelerate (skip locations) or decelerate (repeat them) relative to the map.
//!
//! Input is a score matrix (`Q x L`, higher = more similar, e.g. co-occurrence scores). It is
//! first normalised per location ([`SequenceParams::normalization`], by default the flow
//! method's floored Eq. 2 on `s + 1`, the same similarity `cooc-flow` solves): a group size is
//! not comparable across locations, since a feature-rich location gathers a large chance group
//! with every query, and a path through such locations otherwise beats the true one. With many
//! keypoints per image this is what decides (`docs/cooc.md`). Each row then becomes a
//! dissimilarity `d_ij = 1 - s_ij / max_j s_ij` (all ones for a row without any score).
//! With `contrast_window = w > 0` that dissimilarity is then contrast-enhanced as SeqSLAM does
//! (the paper keeps SeqSLAM's parameters apart from the path shape): each `d_ij` becomes
//! `(d_ij - mean) / std` over its `w` neighbours along the location axis
//! ([`crate::baselines::enhance_contrast`]), shifted to a minimum of 0 and scaled to a maximum
//! of 1. With many keypoints per image every location scores a few correspondences, a row's
//! maximum says little about its background, and the local contrast restores it.
//! For query `i` the window is queries `i+1-length ..= i`. A path starts at every location `j` in
//! the window's first query and, for each next query, greedily steps to the location with the
//! lowest dissimilarity among `pos ..= pos + max_step` (never backwards; ties to the nearest) —
//! the paper's "chooses the image pair with the lowest dissimilarity at each step". The path with
//! the lowest summed dissimilarity wins and its last location is the prediction for query `i`.
//!
//! Confidence: the margin between the best path and the best path ending more than `exclusion`
//! locations away, per query of the window (`(second - best) / window`, in `[0, 1]`): SeqSLAM's
//! uniqueness idea, which is a far better confidence than the raw score on cross-season data.
//!
//! Invariants: paths never move backwards nor by more than `max_step` per query; predictions are
//! one per query, in query order, with finite confidences.

use rayon::prelude::*;

use crate::localize::Prediction;
use crate::similarity::Normalization;
use crate::{Error, Matrix, Result};

/// Settings of [`match_sequences`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SequenceParams {
    /// Queries per window (SeqSLAM's `ds`).
    pub length: usize,
    /// Largest forward step per query, in locations (0 = standing still only).
    pub max_step: usize,
    /// Paths ending within this many locations of the best do not count as the runner-up.
    pub exclusion: usize,
    /// SeqSLAM's local contrast enhancement of the dissimilarities over this many locations
    /// (0 = off: the row-max dissimilarity only; otherwise at least 2).
    pub contrast_window: usize,
    /// Per-location normalisation of the scores before the dissimilarity: `None` uses the raw
    /// scores; `Columns` / `FlooredColumns` divide `s + 1` by its column mean (Eq. 2 of the
    /// flow paper, floored as [`crate::similarity::normalize_columns_floored`] floors it).
    pub normalization: Normalization,
}

impl Default for SequenceParams {
    fn default() -> Self {
        SequenceParams {
            length: 10,
            max_step: 3,
            exclusion: 10,
            contrast_window: 0,
            normalization: Normalization::FlooredColumns,
        }
    }
}

impl SequenceParams {
    /// Fails with [`Error::InvalidParameter`] naming the first out-of-range parameter.
    pub fn validate(&self) -> Result<()> {
        if self.length == 0 {
            return Err(Error::param("length", "a sequence needs at least 1 query"));
        }
        if self.max_step == 0 {
            return Err(Error::param(
                "max_step",
                "must be at least 1 (0 would forbid any forward motion)",
            ));
        }
        if self.contrast_window == 1 {
            return Err(Error::param(
                "contrast_window",
                "must be 0 (off) or at least 2 locations",
            ));
        }
        Ok(())
    }
}

/// Rejects negative or non-finite scores.
fn check_scores(scores: &Matrix) -> Result<()> {
    scores.check_finite("co-occurrence score matrix")?;
    for i in 0..scores.rows() {
        let row = scores.row(i);
        if let Some(j) = row.iter().position(|&v| v < 0.0) {
            return Err(Error::param(
                "scores",
                format!("score ({i}, {j}) is negative ({})", row[j]),
            ));
        }
    }
    Ok(())
}

/// Row-wise dissimilarities `1 - s / max(row)` of checked scores.
fn dissimilarity(scores: &Matrix) -> Matrix {
    let mut d = Matrix::zeros(scores.rows(), scores.cols());
    for i in 0..scores.rows() {
        let row = scores.row(i);
        let max = row.iter().copied().fold(0.0f32, f32::max);
        for (o, &v) in d.row_mut(i).iter_mut().zip(row) {
            *o = if max > 0.0 { 1.0 - v / max } else { 1.0 };
        }
    }
    d
}

/// SeqSLAM's local contrast enhancement of the dissimilarities `d`, scaled back to `[0, 1]`.
fn contrast_enhanced(d: &Matrix, window: usize) -> Result<Matrix> {
    // enhance_contrast takes a similarity c and works on 1 - c = d.
    let mut similarity = d.clone();
    similarity
        .as_mut_slice()
        .iter_mut()
        .for_each(|v| *v = 1.0 - *v);
    let mut e = crate::baselines::enhance_contrast(&similarity, window)?;
    let max = e.as_slice().iter().copied().fold(0.0f32, f32::max);
    if max > 0.0 {
        e.as_mut_slice().iter_mut().for_each(|v| *v /= max);
    }
    Ok(e)
}

/// The greedy forward path from location `start` over rows `first..=last`: (cost, end).
#[inline]
fn greedy_path(
    d: &Matrix,
    first: usize,
    last: usize,
    start: usize,
    max_step: usize,
) -> (f32, usize) {
    let l = d.cols();
    let mut pos = start;
    let mut cost = d.get(first, start);
    for t in first + 1..=last {
        let row = d.row(t);
        let hi = (pos + max_step).min(l - 1);
        let mut best = (row[pos], pos);
        for (k, &v) in row.iter().enumerate().take(hi + 1).skip(pos + 1) {
            if v < best.0 {
                best = (v, k);
            }
        }
        cost += best.0;
        pos = best.1;
    }
    (cost, pos)
}

/// One prediction per query from a `Q x L` score matrix (higher = more similar).
pub fn match_sequences(scores: &Matrix, params: &SequenceParams) -> Result<Vec<Prediction>> {
    params.validate()?;
    if scores.cols() == 0 {
        return Err(Error::Empty("the score matrix has no locations".into()));
    }
    check_scores(scores)?;
    let mut d = match params.normalization {
        Normalization::None => dissimilarity(scores),
        n => {
            let mut shifted = scores.clone();
            shifted.as_mut_slice().iter_mut().for_each(|v| *v += 1.0);
            dissimilarity(&n.apply(&shifted)?)
        }
    };
    if params.contrast_window > 0 {
        d = contrast_enhanced(&d, params.contrast_window)?;
    }
    let l = d.cols();
    let predictions = (0..d.rows())
        .into_par_iter()
        .map(|i| {
            let first = (i + 1).saturating_sub(params.length);
            let window = (i - first + 1) as f32;
            // Best cost per end location.
            let mut end_cost = vec![f32::INFINITY; l];
            for start in 0..l {
                let (c, end) = greedy_path(&d, first, i, start, params.max_step);
                if c < end_cost[end] {
                    end_cost[end] = c;
                }
            }
            let (best_end, best) =
                end_cost
                    .iter()
                    .copied()
                    .enumerate()
                    .fold(
                        (0, f32::INFINITY),
                        |acc, (j, c)| if c < acc.1 { (j, c) } else { acc },
                    );
            let second = end_cost
                .iter()
                .enumerate()
                .filter(|&(j, _)| j.abs_diff(best_end) > params.exclusion)
                .map(|(_, &c)| c)
                .fold(window, f32::min);
            Prediction {
                query: i,
                reference: best_end,
                confidence: f64::from(((second - best) / window).clamp(0.0, 1.0)),
                p_correct: None,
            }
        })
        .collect();
    Ok(predictions)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Scores with a single bright path: query `i` matches location `path[i]`.
    fn path_scores(locations: usize, path: &[usize], noise_seed: u64) -> Matrix {
        let mut rng = crate::cooc::SplitMix64::new(noise_seed);
        let mut s = Matrix::zeros(path.len(), locations);
        for (i, &p) in path.iter().enumerate() {
            for j in 0..locations {
                s.set(i, j, (rng.next_f64() * 4.0) as f32);
            }
            s.set(i, p, 6.0);
        }
        s
    }

    #[test]
    fn follows_an_accelerating_then_stopping_drive() {
        // Speeds 1, 2, 3, then standing still: a constant-velocity SeqSLAM line cannot follow.
        let path = [5, 6, 7, 9, 11, 13, 16, 19, 22, 22, 22, 22, 23, 24];
        let s = path_scores(40, &path, 1);
        let p = match_sequences(&s, &SequenceParams::default()).unwrap();
        for (pred, &truth) in p.iter().zip(&path).skip(3) {
            assert_eq!(pred.reference, truth, "query {}", pred.query);
            assert!(pred.confidence > 0.0);
        }
    }

    #[test]
    fn sequence_beats_single_image_under_noise() {
        // The true location scores 6, but every query has a random decoy scoring 7.
        let path: Vec<usize> = (0..30).map(|i| 10 + i).collect();
        let mut s = path_scores(80, &path, 2);
        let mut rng = crate::cooc::SplitMix64::new(9);
        for i in 0..path.len() {
            s.set(i, rng.below(80), 7.0);
        }
        let single = (0..path.len())
            .filter(|&i| {
                let r = s.row(i);
                let arg = (0..80).fold(0, |b, j| if r[j] > r[b] { j } else { b });
                arg == path[i]
            })
            .count();
        let p = match_sequences(&s, &SequenceParams::default()).unwrap();
        let seq = p
            .iter()
            .skip(5)
            .filter(|x| x.reference == path[x.query])
            .count();
        assert!(
            single < 5,
            "decoys should fool single-image matching ({single})"
        );
        assert!(
            seq >= path.len() - 8,
            "sequence matching found only {seq} of {}",
            path.len() - 5
        );
    }

    proptest::proptest! {
        #[test]
        fn paths_only_move_forward_within_max_step(
            seed in 0u64..1000, start in 0usize..15, rows in 1usize..8, max_step in 1usize..4,
        ) {
            let mut rng = crate::cooc::SplitMix64::new(seed);
            let data = (0..rows * 15).map(|_| rng.next_f64() as f32).collect();
            let d = Matrix::from_vec(rows, 15, data).unwrap();
            let (cost, end) = greedy_path(&d, 0, rows - 1, start, max_step);
            proptest::prop_assert!(end >= start);
            proptest::prop_assert!(end <= (start + max_step * (rows - 1)).min(14));
            proptest::prop_assert!(cost.is_finite() && cost >= 0.0 && cost <= rows as f32);
        }
    }

    #[test]
    fn contrast_enhancement_finds_the_route_over_a_busy_background() {
        // Every location scores a few correspondences; a band of locations scores many for every
        // query (a repetitive place). The true path is only a local peak on its background.
        let path: Vec<usize> = (0..20).map(|i| 30 + i).collect();
        let mut rng = crate::cooc::SplitMix64::new(4);
        let mut s = Matrix::zeros(path.len(), 80);
        for (i, &p) in path.iter().enumerate() {
            for j in 0..80 {
                let base = if (5..15).contains(&j) { 9.0 } else { 2.0 };
                s.set(i, j, base + (rng.next_f64() * 2.0) as f32);
            }
            s.set(i, p, 6.0);
        }
        let found = |contrast_window| {
            let p = SequenceParams {
                contrast_window,
                normalization: Normalization::None,
                ..SequenceParams::default()
            };
            let out = match_sequences(&s, &p).unwrap();
            assert!(out.iter().all(|x| (0.0..=1.0).contains(&x.confidence)));
            out.iter()
                .skip(9)
                .filter(|x| x.reference == path[x.query])
                .count()
        };
        assert!(found(0) < 3, "the busy band should win without contrast");
        assert!(
            found(10) >= 10,
            "contrast enhancement finds the windowed queries"
        );
    }

    #[test]
    fn column_normalisation_discounts_locations_that_match_every_query() {
        // Feature-rich locations 5..15 gather a chance group of 9-11 with every query; the true
        // locations score 6 with their query and 0-4 with the others.
        let path: Vec<usize> = (0..20).map(|i| 30 + i).collect();
        let mut rng = crate::cooc::SplitMix64::new(5);
        let mut s = Matrix::zeros(path.len(), 80);
        for (i, &p) in path.iter().enumerate() {
            for j in 0..80 {
                let base = if (5..15).contains(&j) { 9.0 } else { 0.0 };
                s.set(
                    i,
                    j,
                    base + (rng.next_f64() * 2.0) as f32
                        + if j == p {
                            0.0
                        } else {
                            2.0 * rng.next_f64() as f32
                        },
                );
            }
            s.set(i, p, 6.0);
        }
        let found = |normalization| {
            let p = SequenceParams {
                normalization,
                ..SequenceParams::default()
            };
            match_sequences(&s, &p)
                .unwrap()
                .iter()
                .skip(9)
                .filter(|x| x.reference == path[x.query])
                .count()
        };
        assert_eq!(
            found(Normalization::None),
            0,
            "raw scores follow the rich band"
        );
        assert_eq!(found(Normalization::FlooredColumns), 11);
        assert_eq!(found(Normalization::Columns), 11);
    }

    #[test]
    fn confidence_is_bounded() {
        let s = path_scores(20, &[10, 9, 8, 7, 6], 3);
        let p = match_sequences(
            &s,
            &SequenceParams {
                length: 5,
                max_step: 2,
                exclusion: 2,
                contrast_window: 0,
                ..SequenceParams::default()
            },
        )
        .unwrap();
        assert_eq!(p.len(), 5);
        assert!(p.iter().all(|x| (0.0..=1.0).contains(&x.confidence)));
        assert!(p.iter().enumerate().all(|(i, x)| x.query == i));
    }

    #[test]
    fn rejects_bad_input() {
        let s = Matrix::from_vec(1, 2, vec![1.0, -1.0]).unwrap();
        let err = match_sequences(&s, &SequenceParams::default())
            .unwrap_err()
            .to_string();
        assert!(err.contains("(0, 1)"), "{err}");
        let s = Matrix::from_vec(1, 1, vec![f32::NAN]).unwrap();
        assert!(matches!(
            match_sequences(&s, &SequenceParams::default()),
            Err(Error::NonFinite { .. })
        ));
        let bad = SequenceParams {
            length: 0,
            ..SequenceParams::default()
        };
        assert!(match_sequences(&Matrix::zeros(1, 1), &bad).is_err());
        let bad = SequenceParams {
            contrast_window: 1,
            ..SequenceParams::default()
        };
        let err = match_sequences(&Matrix::zeros(1, 1), &bad).unwrap_err();
        assert!(err.to_string().contains("contrast_window"), "{err}");
    }
}
