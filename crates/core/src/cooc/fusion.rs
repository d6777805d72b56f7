//! Fusing the score rows of a map built from several drives: each drive time is one *source*,
//! scored and normalised on its own as a map of that drive alone would be, and each query's row
//! is taken from the source that recognises it most decisively ([`decisiveness`],
//! [`source_order`]), so a drive added to a map cannot change the rows of queries the map
//! already recognises decisively (`docs/cooc.md`, session 7). Pure matrix work on the per-source
//! score matrices [`super::CoocMap::score_matrices_by_source`] gives; the map and the methods
//! call it.

use crate::{Error, Matrix, Result};

/// How decisively one source recognises one query: how far the row's peak stands above the
/// source's own off-peak scores, `(peak - mean) / max(sd, 1)`, where the off-peak scores are
/// those of the source's locations (`present`) more than `exclusion` locations from the peak
/// (its neighbours show the same place). Without off-peak locations the mean is 0.
///
/// Why: each source (drive time) has a chance level and a spread of its own at every query (a
/// drive at another time of day gathers chance groups everywhere and no peak), so raw peaks
/// are not comparable across sources, but the distance of a peak from the source's own noise
/// is. On raw group sizes this is a z-score with the spread floored at one correspondence, the
/// resolution of a group size. On the floored-normalised rows the fused methods rank sources on
/// ([`fused_similarity`], [`fused_scores`]) every off-peak spread is below 1 (0.14-0.58 on
/// Gardens Point dev), so there the floor binds and this is the peak's excess over the row's
/// off-peak mean in units of a location's mean score, which the normalisation already puts on
/// one scale for every source; a plain z-score there was measured and chose no better
/// (`docs/cooc.md`, session 12).
pub fn decisiveness(row: &[f32], present: &[bool], exclusion: usize) -> f32 {
    let Some((peak_at, peak)) = row_peak(row, present) else {
        return 0.0;
    };
    let (mean, sd) = off_peak_noise(row, present, peak_at, exclusion);
    ((f64::from(peak) - mean) / sd) as f32
}

/// The row's peak over the source's locations (`present`): `(location, score)`, the first one
/// on ties; `None` when the source has no location.
pub fn row_peak(row: &[f32], present: &[bool]) -> Option<(usize, f32)> {
    row.iter()
        .zip(present)
        .enumerate()
        .filter(|(_, (_, &p))| p)
        .map(|(j, (&v, _))| (j, v))
        .fold(None, |best: Option<(usize, f32)>, (j, v)| match best {
            Some((_, b)) if b >= v => best,
            _ => Some((j, v)),
        })
}

/// The mean and spread of the row's off-peak scores as [`decisiveness`] measures them: the
/// source's locations (`present`) more than `exclusion` from `peak_at`, the spread floored at
/// 1; `(0, 1)` without such locations.
pub fn off_peak_noise(
    row: &[f32],
    present: &[bool],
    peak_at: usize,
    exclusion: usize,
) -> (f64, f64) {
    off_peak_stats(row, present, peak_at, exclusion)
        .map_or((0.0, 1.0), |(mean, sd)| (mean, sd.max(1.0)))
}

/// The mean and the spread (no floor) of the row's off-peak scores: the source's locations
/// (`present`) more than `exclusion` from `peak_at`; `None` without such locations.
pub fn off_peak_stats(
    row: &[f32],
    present: &[bool],
    peak_at: usize,
    exclusion: usize,
) -> Option<(f64, f64)> {
    let (mut n, mut sum, mut sq) = (0usize, 0f64, 0f64);
    for (j, (&v, &p)) in row.iter().zip(present).enumerate() {
        if p && j.abs_diff(peak_at) > exclusion {
            n += 1;
            sum += f64::from(v);
            sq += f64::from(v) * f64::from(v);
        }
    }
    if n == 0 {
        return None;
    }
    let mean = sum / n as f64;
    Some((mean, (sq / n as f64 - mean * mean).max(0.0).sqrt()))
}

/// Per query, the sources of a fused map from the most to the least decisive: the mean
/// [`decisiveness`] of each source's rows in `per_source` (the fused methods pass the
/// floored-normalised rows, [`normalise_sources`]) over the `window` queries centred on the
/// query (`window` 1: the query alone; clipped at the ends of the sequence); ties to the lower
/// source index.
///
/// Why: a fused map must keep the evidence of the drives that already recognise a query. Taking
/// the best source per location lets a drive the query does not resemble add its chance peaks
/// to every wrong location; choosing the source whose peaks stand out most from its own noise
/// leaves a query run that one drive recognises decisively with exactly that drive's scores,
/// and lets an added drive speak only where it recognises the run more decisively. A window
/// (the sequence matching's length) makes the choice one per stretch of the route: where no
/// drive is decisive, one query's decisiveness is noise and choosing per query would switch
/// sources from frame to frame (`docs/cooc.md`, measured).
pub fn source_order(
    per_source: &[Matrix],
    present: &[bool],
    exclusion: usize,
    window: usize,
) -> Result<Vec<Vec<usize>>> {
    let (q, l) = check_sources(per_source, present)?;
    let d: Vec<Vec<f64>> = per_source
        .iter()
        .enumerate()
        .map(|(s, m)| {
            (0..q)
                .map(|i| {
                    f64::from(decisiveness(
                        m.row(i),
                        &present[s * l..(s + 1) * l],
                        exclusion,
                    ))
                })
                .collect()
        })
        .collect();
    Ok(rank_sources(&d, window))
}

/// The window of [`rank_sources`] (and [`source_order`], [`fused_scores`]) that is the whole
/// batch for every query: one source for all its rows. Single-image recognition on a fused map
/// chooses its source this way (`CoocQueries`' single-image method).
pub const WHOLE_BATCH: usize = usize::MAX;

/// Per query, the sources from the highest to the lowest mean of `d[source][query]` over the
/// `window` queries centred on the query (clipped at the ends of the sequence, so a window of
/// `2Q - 1` or more, [`WHOLE_BATCH`], is every query); ties to the lower source index.
/// [`source_order`] ranks on [`decisiveness`] this way.
pub fn rank_sources(d: &[Vec<f64>], window: usize) -> Vec<Vec<usize>> {
    let q = d.first().map_or(0, Vec::len);
    let w = window.max(1);
    (0..q)
        .map(|i| {
            let lo = i.saturating_sub((w - 1) / 2);
            let hi = lo.saturating_add(w).min(q);
            let mean: Vec<f64> = d
                .iter()
                .map(|ds| ds[lo..hi].iter().sum::<f64>() / (hi - lo) as f64)
                .collect();
            let mut order: Vec<usize> = (0..d.len()).collect();
            order.sort_by(|&a, &b| mean[b].total_cmp(&mean[a]).then(a.cmp(&b)));
            order
        })
        .collect()
}

/// Checks that `per_source` are `Q x L` matrices and `present` has `sources x L` flags;
/// returns `(Q, L)`.
pub fn check_sources(per_source: &[Matrix], present: &[bool]) -> Result<(usize, usize)> {
    let Some(first) = per_source.first() else {
        return Err(Error::Empty("no score matrix to fuse".into()));
    };
    let (q, l) = (first.rows(), first.cols());
    if present.len() != per_source.len() * l
        || per_source.iter().any(|m| m.cols() != l || m.rows() != q)
    {
        return Err(Error::Shape(format!(
            "{} score matrices of {q}x{l} and {} presence flags do not match",
            per_source.len(),
            present.len()
        )));
    }
    Ok((q, l))
}

/// Row `i` of the fused matrix takes every location from the first source in `order[i]` that
/// has it (`present`); a location no source has keeps source 0's value.
pub fn fuse_rows(per_source: &[Matrix], present: &[bool], order: &[Vec<usize>]) -> Matrix {
    let (q, l) = (per_source[0].rows(), per_source[0].cols());
    let mut out = per_source[0].clone();
    for (i, sources) in order.iter().enumerate().take(q) {
        let dst = out.row_mut(i);
        for (j, o) in dst.iter_mut().enumerate() {
            if let Some(&s) = sources.iter().find(|&&s| present[s * l + j]) {
                *o = per_source[s].get(i, j);
            }
        }
    }
    out
}

/// The raw scores of a fused map as one `Q x L` matrix: each query's row from the source
/// that is most decisive on the rows [`fused_similarity`] gives under `normalization`
/// ([`source_order`] with `exclusion` and `window`). Single-image recognition on a fused map
/// takes its best location from this row (window [`WHOLE_BATCH`]); with one source it is that
/// source's scores.
pub fn fused_scores(
    per_source: &[Matrix],
    present: &[bool],
    normalization: crate::similarity::Normalization,
    exclusion: usize,
    window: usize,
) -> Result<Matrix> {
    let normalised = normalise_sources(per_source, present, normalization)?;
    let order = source_order(&normalised, present, exclusion, window)?;
    Ok(fuse_rows(per_source, present, &order))
}

/// Each source's [`super::flow_similarity`] normalised on its own over its locations (`present`) and
/// all queries, as a map of that drive alone would normalise it; `Q x L` each, 0 where the
/// source has no training set.
pub fn normalise_sources(
    per_source: &[Matrix],
    present: &[bool],
    normalization: crate::similarity::Normalization,
) -> Result<Vec<Matrix>> {
    let (q, l) = check_sources(per_source, present)?;
    let mut normalised = Vec::with_capacity(per_source.len());
    for (d, s) in per_source.iter().enumerate() {
        let cols: Vec<usize> = (0..l).filter(|&j| present[d * l + j]).collect();
        let mut full = Matrix::zeros(q, l);
        if !cols.is_empty() {
            let mut c = Matrix::zeros(q, cols.len());
            for i in 0..q {
                let (src, dst) = (s.row(i), c.row_mut(i));
                for (o, &j) in dst.iter_mut().zip(&cols) {
                    *o = src[j] + 1.0;
                }
            }
            let c = normalization.apply(&c)?;
            for i in 0..q {
                let (src, dst) = (c.row(i), full.row_mut(i));
                for (&v, &j) in src.iter().zip(&cols) {
                    dst[j] = v;
                }
            }
        }
        normalised.push(full);
    }
    Ok(normalised)
}

/// The similarity `ĉ` the sequence matching and the flow graph use on a map fused from
/// several drives: each source's scores ([`super::CoocMap::score_matrices_by_source`]) become
/// [`super::flow_similarity`] and are normalised over that source's locations (`present`, from
/// [`super::LocationMap::source_present`]) and over all queries, as a map of that drive alone would
/// normalise them; then each query's row is its most decisive source's ([`source_order`],
/// with `exclusion` and `window`). With one source this is `normalization` applied to [`super::flow_similarity`] of
/// the scores, as before.
///
/// Why per source and per query: a drive the queries do not resemble (night for day queries)
/// only adds chance groups, at a chance level of its own. Normalising each drive's evidence on
/// its own keeps their scales comparable, and taking each query's row from one source keeps
/// the rows of a query that a drive recognises decisively exactly what that drive alone gives:
/// fusing a drive cannot lower them (`docs/cooc.md`, measured; the best source per location,
/// session 5, still lost up to 0.098 AP on single vocabularies).
pub fn fused_similarity(
    per_source: &[Matrix],
    present: &[bool],
    normalization: crate::similarity::Normalization,
    exclusion: usize,
    window: usize,
) -> Result<Matrix> {
    let normalised = normalise_sources(per_source, present, normalization)?;
    // Decisiveness is measured on the rows the methods read: a location that gathers chance
    // groups with every query (feature-rich) is discounted by the normalisation, so its peaks
    // do not pass for recognition.
    let order = source_order(&normalised, present, exclusion, window)?;
    Ok(fuse_rows(&normalised, present, &order))
}

#[cfg(test)]
mod tests {
    use super::super::map::flow_similarity;
    use super::*;
    use crate::similarity::Normalization;

    #[test]
    fn fused_similarity_of_one_source_is_the_normalised_flow_similarity() {
        let mut rng = crate::cooc::SplitMix64::new(3);
        let data = (0..6 * 9).map(|_| rng.below(7) as f32).collect();
        let s = Matrix::from_vec(6, 9, data).unwrap();
        for n in [
            Normalization::None,
            Normalization::Columns,
            Normalization::FlooredColumns,
        ] {
            let fused = fused_similarity(std::slice::from_ref(&s), &[true; 9], n, 2, 3).unwrap();
            assert_eq!(fused, n.apply(&flow_similarity(&s)).unwrap(), "{n:?}");
        }
        let raw = fused_scores(
            std::slice::from_ref(&s),
            &[true; 9],
            Normalization::FlooredColumns,
            2,
            3,
        )
        .unwrap();
        assert_eq!(raw, s);
        let err = fused_similarity(&[s], &[true; 3], Normalization::None, 2, 1).unwrap_err();
        assert!(err.to_string().contains("presence"), "{err}");
        assert!(fused_similarity(&[], &[], Normalization::None, 2, 1).is_err());
    }

    #[test]
    fn decisiveness_is_the_peak_over_the_sources_own_off_peak_noise() {
        let all = [true; 8];
        // A flat row has no peak; a row without any location has none either.
        assert_eq!(decisiveness(&[3.0; 8], &all, 1), 0.0);
        assert_eq!(decisiveness(&[3.0; 8], &[false; 8], 1), 0.0);
        // Peak 10 at 2; its neighbours (1, 3) are not noise; off-peak 0, 2, 0, 2, 0: mean 0.8,
        // sd 0.98 floored at 1 -> 9.2.
        let row = [0.0, 9.0, 10.0, 9.0, 2.0, 0.0, 2.0, 0.0];
        assert!((decisiveness(&row, &all, 1) - 9.2).abs() < 1e-5);
        // The same peak over a noisier source stands out less.
        let noisy = [0.0, 9.0, 10.0, 9.0, 8.0, 0.0, 8.0, 0.0];
        assert!(decisiveness(&noisy, &all, 1) < decisiveness(&row, &all, 1));
        // Shifting or scaling a row's scores by the source's chance level does not change it
        // (spread above the floor).
        let shifted: Vec<f32> = noisy.iter().map(|v| v * 2.0 + 5.0).collect();
        let d = decisiveness(&noisy, &all, 1);
        assert!((decisiveness(&shifted, &all, 1) - d).abs() < 1e-5);
        // Locations the source has no training set of are neither peak nor noise.
        let mut present = all;
        present[2] = false;
        // Peak 9 at 1 (the first of two); off-peak 3..8: 9, 2, 0, 2, 0.
        let d = decisiveness(&row, &present, 1);
        assert!((d - (9.0 - 2.6) / 11.04f32.sqrt()).abs() < 1e-4, "{d}");
        // Ranking: per query, most decisive first, ties to the lower source.
        let a = Matrix::from_vec(2, 8, [row, [1.0; 8]].concat()).unwrap();
        let b = Matrix::from_vec(2, 8, [noisy, [1.0; 8]].concat()).unwrap();
        let order = source_order(&[b.clone(), a.clone()], &[true; 16], 1, 1).unwrap();
        assert_eq!(order, vec![vec![1, 0], vec![0, 1]]);
        // Over a window of 3 queries, query 1 (no peak anywhere) follows its neighbour's choice.
        let order = source_order(&[b, a], &[true; 16], 1, 3).unwrap();
        assert_eq!(order, vec![vec![1, 0], vec![1, 0]]);
    }

    #[test]
    fn a_source_the_queries_do_not_resemble_cannot_outvote_the_one_they_do() {
        // Source 0 (day): query i scores 6 at location i, 0-2 elsewhere. Source 1 (night): no
        // true match, but a chance level of 5-8 everywhere, higher at some locations.
        let (q, l) = (8, 12);
        let mut rng = crate::cooc::SplitMix64::new(11);
        let mut day = Matrix::zeros(q, l);
        let mut night = Matrix::zeros(q, l);
        for i in 0..q {
            for j in 0..l {
                day.set(i, j, rng.below(3) as f32);
                night.set(i, j, 5.0 + rng.below(4) as f32);
            }
            day.set(i, i, 6.0);
        }
        let argmax = |m: &Matrix| -> Vec<usize> {
            (0..q)
                .map(|i| (0..l).fold(0, |b, j| if m.get(i, j) > m.get(i, b) { j } else { b }))
                .collect()
        };
        let truth: Vec<usize> = (0..q).collect();
        let mut raw_max = day.clone();
        for (a, &b) in raw_max.as_mut_slice().iter_mut().zip(night.as_slice()) {
            *a = a.max(b);
        }
        let raw_hits = argmax(&raw_max)
            .iter()
            .zip(&truth)
            .filter(|(a, b)| a == b)
            .count();
        assert!(
            raw_hits < q / 2,
            "the night chance level wins the raw maximum ({raw_hits})"
        );
        let present = vec![true; 2 * l];
        let fused = fused_similarity(
            &[day.clone(), night.clone()],
            &present,
            Normalization::FlooredColumns,
            1,
            3,
        )
        .unwrap();
        assert_eq!(argmax(&fused), truth);
        assert_eq!(
            argmax(
                &fused_scores(
                    &[day.clone(), night.clone()],
                    &present,
                    Normalization::FlooredColumns,
                    1,
                    1
                )
                .unwrap()
            ),
            truth
        );
        // Every row is the day source's alone, normalised as a map of the day drive would.
        let day_alone = Normalization::FlooredColumns
            .apply(&flow_similarity(&day))
            .unwrap();
        assert_eq!(fused, day_alone);
        // A location the most decisive source did not see takes the next source's value.
        let mut present = present;
        present[3] = false;
        let raw = fused_scores(&[day, night.clone()], &present, Normalization::None, 1, 1).unwrap();
        assert_eq!(raw.get(0, 3), night.get(0, 3));
        assert_eq!(raw.get(0, 0), 6.0);
    }

    #[test]
    fn the_whole_batch_reads_every_query_from_the_source_it_resembles_most() {
        // Source 0 (the map's drive): query i peaks at location i, 5 over a chance level of
        // 0-1. Source 1 (an added drive of similar conditions): a peak at the wrong location
        // i + 3, 9 high for queries 2 and 5 (more decisive there than source 0) and 2
        // elsewhere.
        let (q, l) = (8, 12);
        let mut rng = crate::cooc::SplitMix64::new(5);
        let mut map = Matrix::zeros(q, l);
        let mut added = Matrix::zeros(q, l);
        for i in 0..q {
            for j in 0..l {
                map.set(i, j, rng.below(2) as f32);
                added.set(i, j, rng.below(2) as f32);
            }
            map.set(i, i, 5.0);
            added.set(i, i + 3, if i == 2 || i == 5 { 9.0 } else { 2.0 });
        }
        let sources = [map.clone(), added.clone()];
        let present = vec![true; 2 * l];
        let n = Normalization::FlooredColumns;
        // One query at a time, some queries (2 and 5 among them) take the added drive's wrong
        // peak ...
        let order = source_order(
            &normalise_sources(&sources, &present, n).unwrap(),
            &present,
            1,
            1,
        )
        .unwrap();
        let firsts: Vec<usize> = order.iter().map(|o| o[0]).collect();
        assert!(firsts[2] == 1 && firsts[5] == 1, "{firsts:?}");
        assert!(
            firsts.iter().filter(|&&s| s == 0).count() > q / 2,
            "{firsts:?}"
        );
        // ... over the whole batch every row is the map's own: what the map alone answered.
        for window in [WHOLE_BATCH, 2 * q - 1] {
            assert_eq!(fused_scores(&sources, &present, n, 1, window).unwrap(), map);
        }
        // The order of the sources does not matter; a batch that resembles the added drive most
        // is read from it alone.
        let swapped = [added.clone(), map.clone()];
        let mut strong = added.clone();
        for i in 0..q {
            strong.set(i, i + 3, 9.0);
        }
        let sources = [map, strong.clone()];
        assert_eq!(
            fused_scores(&sources, &present, n, 1, WHOLE_BATCH).unwrap(),
            strong
        );
        assert_eq!(
            fused_scores(&swapped, &present, n, 1, WHOLE_BATCH).unwrap(),
            swapped[1]
        );
    }
}
