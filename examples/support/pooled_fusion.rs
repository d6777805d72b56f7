//! Session 10's alternative fusion rule for maps built from several drives, measured by
//! `cooc_gardens` against the shipped one and not adopted (`docs/cooc.md`, session 10): instead
//! of each query window taking the rows of its most decisive source
//! (`seasonloc_core::cooc::fused_similarity`), every source's standardised row is combined with the
//! others, weighted by its signal-to-noise estimate (maximum-ratio combining). Kept here so the
//! session's table can be reproduced. Session 12's variant of the shipped rule (the
//! decisiveness's spread floor, [`floored_aps`]) is here for the same reason.

use seasonloc_core::cooc::{
    best_per_query, check_sources, fuse_rows, normalise_sources, off_peak_noise, off_peak_stats,
    rank_sources, row_peak, source_order, CoocMap, CoocOptions, CoocQueries, SequenceParams,
};
use seasonloc_core::eval::{evaluate, Exclusions, GroundTruth};
use seasonloc_core::similarity::Normalization;
use seasonloc_core::{Error, Matrix, Result};

/// The noise of one source's row: its peak, the mean and spread of its off-peak scores (as
/// `seasonloc_core::cooc::decisiveness` measures them) and the best off-peak score (the runner-up). `None` when the
/// source has no location.
#[derive(Clone, Copy, Debug, PartialEq)]
struct RowNoise {
    peak: f64,
    mean: f64,
    sd: f64,
    runner_up: f64,
    third: f64,
}

impl RowNoise {
    fn of(row: &[f32], present: &[bool], exclusion: usize) -> Option<RowNoise> {
        let (peak_at, peak) = row_peak(row, present)?;
        let (mean, sd) = off_peak_noise(row, present, peak_at, exclusion);
        let mut runner_up: Option<(usize, f64)> = None;
        for (j, (&v, &p)) in row.iter().zip(present).enumerate() {
            if p && j.abs_diff(peak_at) > exclusion
                && runner_up.is_none_or(|(_, r)| f64::from(v) > r)
            {
                runner_up = Some((j, f64::from(v)));
            }
        }
        let third = runner_up.and_then(|(at, _)| {
            row.iter()
                .zip(present)
                .enumerate()
                .filter(|(j, (_, &p))| {
                    p && j.abs_diff(peak_at) > exclusion && j.abs_diff(at) > exclusion
                })
                .map(|(_, (&v, _))| f64::from(v))
                .reduce(f64::max)
        });
        Some(RowNoise {
            peak: f64::from(peak),
            mean,
            sd,
            runner_up: runner_up.map_or(mean, |(_, r)| r),
            third: third.or(runner_up.map(|(_, r)| r)).unwrap_or(mean),
        })
    }

    /// `seasonloc_core::cooc::decisiveness`: the peak's z-score over the off-peak noise.
    fn decisiveness(&self) -> f64 {
        (self.peak - self.mean) / self.sd
    }

    /// The peak's margin over the runner-up in units of the spread: the estimate of the
    /// source's signal-to-noise ratio (the peak's z-score minus the level the source's own
    /// noise reaches in the same row, which is what a source without the place peaks at).
    fn margin(&self) -> f64 {
        (self.peak - self.runner_up) / self.sd
    }

    /// [`RowNoise::margin`] less what noise alone gives it: the top spacings of `n` noise
    /// scores are, by extreme-value theory (Gumbel tail, scale `b`), independent with
    /// `E[x1 - x2] = b` and `E[x2 - x3] = b / 2`, so `(x1 - x2) - 2 (x2 - x3)` has mean 0 for a
    /// source without the place, and the peak's excess over its noise for one with it.
    fn excess_margin(&self) -> f64 {
        ((self.peak - self.runner_up) - 2.0 * (self.runner_up - self.third)) / self.sd
    }
}

/// The signal-to-noise estimate [`pooled_rows`] weighs a source by.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PoolWeight {
    /// The peak's margin over the runner-up, in units of the off-peak spread.
    Margin,
    /// The peak's z-score over the off-peak noise (`seasonloc_core::cooc::decisiveness`).
    Decisiveness,
    /// The margin less its expectation under noise alone (`RowNoise::excess_margin`).
    ExcessMargin,
}

/// The maximum-ratio combination of the sources' rows (`docs/cooc.md`, session 10; measured, not adopted): per query
/// and source, `rows` standardised over their own off-peak noise (`z = (x - mean) / sd`, as
/// `seasonloc_core::cooc::decisiveness` measures it), weighted by the source's signal-to-noise ratio `w`, the mean
/// over `window` queries centred on the query of the peak's margin over its runner-up on the
/// `ranking` rows ([`RowNoise::margin`]); the fused value `Σ w z / sqrt(Σ w²)` (unit noise when
/// the sources' noises are independent) is put back on the sources' scale, `mean* + sd* · f`
/// with `mean*`, `sd*` the sources' means and spreads weighted by `w²`. A location only one
/// weighted source has takes that source's value as it is, so a query whose weight rests on one
/// source keeps that source's row exactly; where no source has weight, the most decisive
/// source's row (as `seasonloc_core::cooc::source_order`).
pub fn pooled_rows(
    rows: &[Matrix],
    ranking: &[Matrix],
    present: &[bool],
    exclusion: usize,
    window: usize,
    weight: PoolWeight,
) -> Result<Matrix> {
    let (q, l) = check_sources(ranking, present)?;
    check_sources(rows, present)?;
    if rows.len() != ranking.len() || rows[0].rows() != q {
        return Err(Error::Shape(format!(
            "{} rows to fuse for {} ranked sources",
            rows.len(),
            ranking.len()
        )));
    }
    let margins: Vec<Vec<f64>> = ranking
        .iter()
        .enumerate()
        .map(|(s, m)| {
            (0..q)
                .map(|i| {
                    RowNoise::of(m.row(i), &present[s * l..(s + 1) * l], exclusion).map_or(
                        0.0,
                        |r| match weight {
                            PoolWeight::Margin => r.margin(),
                            PoolWeight::Decisiveness => r.decisiveness(),
                            PoolWeight::ExcessMargin => r.excess_margin(),
                        },
                    )
                })
                .collect()
        })
        .collect();
    let order = source_order(ranking, present, exclusion, window)?;
    let w = window.max(1);
    let mut out = Matrix::zeros(q, l);
    for (i, ranked) in order.iter().enumerate() {
        let lo = i.saturating_sub((w - 1) / 2);
        let hi = lo.saturating_add(w).min(q);
        let weights: Vec<f64> = margins
            .iter()
            .map(|m| (m[lo..hi].iter().sum::<f64>() / (hi - lo) as f64).max(0.0))
            .collect();
        let noise: Vec<Option<RowNoise>> = rows
            .iter()
            .enumerate()
            .map(|(s, m)| RowNoise::of(m.row(i), &present[s * l..(s + 1) * l], exclusion))
            .collect();
        let dst = out.row_mut(i);
        for (j, o) in dst.iter_mut().enumerate() {
            let weighted: Vec<(usize, f64, RowNoise)> = (0..rows.len())
                .filter(|&s| present[s * l + j] && weights[s] > 0.0)
                .filter_map(|s| noise[s].map(|r| (s, weights[s], r)))
                .collect();
            *o = match weighted.as_slice() {
                [] => ranked
                    .iter()
                    .find(|&&s| present[s * l + j])
                    .map_or(0.0, |&s| rows[s].get(i, j)),
                [(s, _, _)] => rows[*s].get(i, j),
                many => {
                    let (mut num, mut w2, mut mean, mut sd) = (0f64, 0f64, 0f64, 0f64);
                    for &(s, ws, r) in many {
                        let z = (f64::from(rows[s].get(i, j)) - r.mean) / r.sd;
                        num += ws * z;
                        w2 += ws * ws;
                        mean += ws * ws * r.mean;
                        sd += ws * ws * r.sd;
                    }
                    ((mean + sd * num / w2.sqrt()) / w2) as f32
                }
            };
        }
    }
    Ok(out)
}

/// AP (tolerance 2) of `cooc`, `cooc-seq` and `cooc-flow` on a fused map with the sources
/// pooled by [`pooled_rows`] (`weight`), each method reading the pooled rows as
/// `CoocQueries::localize` reads the fused ones: `cooc` the best location of the pooled raw
/// scores (weights on the floored-normalised rows, window 1), `cooc-seq` and `cooc-flow` the
/// pooled normalised rows over the fusion window.
pub fn pooled_aps(
    map: &CoocMap,
    queries: &CoocQueries,
    options: &CoocOptions,
    weight: PoolWeight,
    gt: &GroundTruth,
    n: usize,
) -> [f64; 3] {
    let per_source = map.score_matrices_by_source(queries.words());
    let present = map.locations().source_present();
    let window = if options.fusion_window == 0 {
        options.sequence.length
    } else {
        options.fusion_window
    };
    let excl = options.sequence.exclusion;
    let pooled = |rows_normalization: Option<Normalization>, ranking: Normalization, window| {
        let ranked = normalise_sources(&per_source, &present, ranking).expect("normalised");
        match rows_normalization {
            None => pooled_rows(&per_source, &ranked, &present, excl, window, weight),
            Some(_) => pooled_rows(&ranked, &ranked, &present, excl, window, weight),
        }
        .expect("pooled rows")
    };
    let single = best_per_query(&pooled(None, Normalization::default(), 1));
    let params = options.sequence;
    let seq_input = if params.normalization == Normalization::None {
        pooled(None, Normalization::None, window)
    } else {
        pooled(Some(params.normalization), params.normalization, window)
    };
    let seq = seasonloc_core::cooc::sequence::match_sequences(
        &seq_input,
        &SequenceParams {
            normalization: Normalization::None,
            ..params
        },
    )
    .expect("sequences");
    let chat = pooled(
        Some(options.flow.normalization),
        options.flow.normalization,
        window,
    );
    let (_, flow) =
        seasonloc_core::localize::solve_with_confidence(&chat, &options.flow).expect("flow");
    [single, seq, flow].map(|p| {
        evaluate(&p, gt, n, 2, &Exclusions::none())
            .expect("metrics")
            .ap
    })
}

/// What [`floored_aps`] measured on one fused map.
pub struct Floored {
    /// AP of `cooc`, `cooc-seq`, `cooc-flow`.
    pub aps: [f64; 3],
    /// Per source, the queries whose row it gave for `cooc` (window 1) and for the sequence
    /// methods (the fusion window).
    pub chosen_single: Vec<usize>,
    pub chosen_window: Vec<usize>,
    /// The 5th, 50th and 95th percentile and the maximum of the rows' off-peak spread (before
    /// any floor), over every source and query.
    pub spread: [f64; 4],
}

/// Session 12 (`docs/cooc.md`): the shipped rule (each query window takes its most decisive source's
/// rows) with the decisiveness spread floored in the units of the rows it is measured on.
/// `floor` `None`: the shipped floor of 1 (one correspondence of a raw score); `Some(0)`: no
/// floor (a plain z-score, 1e-9 against division by zero); `Some(1)`: one correspondence in
/// normalised units, `1 / median_j m_j` with `m_j` the source's column means of `s + 1`.
pub fn floored_aps(
    map: &CoocMap,
    queries: &CoocQueries,
    options: &CoocOptions,
    floor: Option<usize>,
    gt: &GroundTruth,
    n: usize,
) -> Floored {
    let per_source = map.score_matrices_by_source(queries.words());
    let present = map.locations().source_present();
    let excl = options.sequence.exclusion;
    let window = if options.fusion_window == 0 {
        options.sequence.length
    } else {
        options.fusion_window
    };
    let (q, l) = check_sources(&per_source, &present).expect("sources");
    let norm = Normalization::default();
    let normalised = normalise_sources(&per_source, &present, norm).expect("normalised");
    let floors: Vec<f64> = per_source
        .iter()
        .enumerate()
        .map(|(s, m)| match floor {
            None => 1.0,
            Some(0) => 1e-9,
            Some(_) => {
                let mut means: Vec<f64> = (0..l)
                    .filter(|&j| present[s * l + j])
                    .map(|j| (0..q).map(|i| f64::from(m.get(i, j)) + 1.0).sum::<f64>() / q as f64)
                    .collect();
                means.sort_by(f64::total_cmp);
                1.0 / means[means.len() / 2].max(1e-9)
            }
        })
        .collect();
    let spreads = std::cell::RefCell::new(Vec::new());
    let d: Vec<Vec<f64>> = normalised
        .iter()
        .enumerate()
        .map(|(s, m)| {
            let p = &present[s * l..(s + 1) * l];
            (0..q)
                .map(|i| {
                    let row = m.row(i);
                    let Some((at, peak)) = row_peak(row, p) else {
                        return 0.0;
                    };
                    let Some((mean, raw_sd)) = off_peak_stats(row, p, at, excl) else {
                        return 0.0;
                    };
                    spreads.borrow_mut().push(raw_sd);
                    let sd = raw_sd.max(floors[s]);
                    (f64::from(peak) - mean) / sd
                })
                .collect()
        })
        .collect();
    let fuse = |rows: &[Matrix], order: &[Vec<usize>]| fuse_rows(rows, &present, order);
    let count = |order: &[Vec<usize>]| {
        let mut c = vec![0usize; per_source.len()];
        order.iter().for_each(|o| c[o[0]] += 1);
        c
    };
    let (o1, ow) = (rank_sources(&d, 1), rank_sources(&d, window));
    let single = best_per_query(&fuse(&per_source, &o1));
    let params = options.sequence;
    let seq = seasonloc_core::cooc::sequence::match_sequences(
        &fuse(&normalised, &ow),
        &SequenceParams {
            normalization: Normalization::None,
            ..params
        },
    )
    .expect("sequences");
    let flow_rows =
        normalise_sources(&per_source, &present, options.flow.normalization).expect("normalised");
    let (_, flow) =
        seasonloc_core::localize::solve_with_confidence(&fuse(&flow_rows, &ow), &options.flow)
            .expect("flow");
    let aps = [single, seq, flow].map(|p| {
        evaluate(&p, gt, n, 2, &Exclusions::none())
            .expect("metrics")
            .ap
    });
    let mut spread = spreads.into_inner();
    spread.sort_by(f64::total_cmp);
    let at = |f: f64| {
        spread
            .get(((spread.len().max(1) - 1) as f64 * f) as usize)
            .copied()
            .unwrap_or(0.0)
    };
    Floored {
        aps,
        chosen_single: count(&o1),
        chosen_window: count(&ow),
        spread: [at(0.05), at(0.5), at(0.95), at(1.0)],
    }
}
