//! Cosine similarity matrix (flow paper Eq. 1) and column normalisation (Eq. 2).
//!
//! [`cosine_matrix`] turns two descriptor sets (one row per image) into the Q x D matrix
//! `c_ij = cos(q_i, d_j)`. Rows are L2-normalised once (O((Q+D)·N)), then the whole matrix is
//! ONE batched product `Q̂ · D̂ᵀ` computed by the `gemm` crate across all rayon threads — no
//! pairwise loops — so the cost is that of a single SGEMM, O(Q·D·N).
//!
//! [`normalize_columns`] divides each column by its mean over all queries (`ĉ_ij = c_ij /
//! mean_i c_ij`), which removes the "this reference image looks like everything" bias before
//! the graph solver turns `ĉ` into costs `1/ĉ`.
//!
//! Invariants and conventions:
//! * Inputs must be non-empty and finite; descriptor lengths must agree.
//! * A zero-norm descriptor (all zeros) has no direction: its similarity with every other
//!   descriptor is defined as 0 (it neither attracts nor repels matches).
//! * Outputs of [`cosine_matrix`] are clamped into `[-1, 1]` (float rounding can overshoot by a
//!   few ulps).
//! * A column whose mean is `<= 1e-12` (zero, negative, or vanishingly small) cannot be
//!   normalised meaningfully; it becomes all zeros, which the solver treats as unusable
//!   (matching nodes with `ĉ <= 0` are unusable).

use rayon::prelude::*;

use crate::{Error, Matrix, Result};

/// Column means at or below this value make the column unusable in [`normalize_columns`].
pub const MIN_COLUMN_MEAN: f64 = 1e-12;

/// The Q x D cosine similarity matrix of `queries` (Q x N) and `references` (D x N).
///
/// Fails with [`Error::Empty`] when either set has no rows or the descriptors have length 0,
/// [`Error::Shape`] when the descriptor lengths differ, and [`Error::NonFinite`] on NaN or
/// infinite input. A zero descriptor has similarity 0 with everything.
pub fn cosine_matrix(queries: &Matrix, references: &Matrix) -> Result<Matrix> {
    check_pair(queries, references)?;
    references.check_finite("reference descriptors")?;
    Ok(normalized_product(queries, &l2_normalized_rows(references)))
}

/// [`cosine_matrix`] against references normalised beforehand with [`l2_normalized_rows`]:
/// the same values bit for bit (the same normalisation, product and clamp), without copying,
/// checking and normalising the reference matrix per call. For a trip's batch of a few frames
/// on a city-scale map (30,790 x 756) that per-call work on the references is about 100 ms,
/// the product itself a few; callers keep the normalised matrix per map version
/// (`app::cache`). `normalized_references` must come from [`l2_normalized_rows`] of finite
/// descriptors (unchecked here).
pub fn cosine_matrix_normalized(
    queries: &Matrix,
    normalized_references: &Matrix,
) -> Result<Matrix> {
    check_pair(queries, normalized_references)?;
    Ok(normalized_product(queries, normalized_references))
}

/// The checks both cosine entry points make, in their order: neither set empty, equal and
/// non-zero descriptor lengths, finite queries.
fn check_pair(queries: &Matrix, references: &Matrix) -> Result<()> {
    if queries.rows() == 0 {
        return Err(Error::Empty("query descriptor set has no rows".into()));
    }
    if references.rows() == 0 {
        return Err(Error::Empty("reference descriptor set has no rows".into()));
    }
    if queries.cols() != references.cols() {
        return Err(Error::Shape(format!(
            "query descriptors have length {}, reference descriptors have length {}",
            queries.cols(),
            references.cols()
        )));
    }
    if queries.cols() == 0 {
        return Err(Error::Empty("descriptors have length 0".into()));
    }
    queries.check_finite("query descriptors")
}

/// The clamped cosines of `queries` (normalised here) against unit-norm reference rows.
fn normalized_product(queries: &Matrix, normalized_references: &Matrix) -> Matrix {
    let qn = l2_normalized_rows(queries);
    let mut out = Matrix::zeros(queries.rows(), normalized_references.rows());
    matmul_abt(&qn, normalized_references, &mut out);
    out.as_mut_slice()
        .par_chunks_mut(4096)
        .for_each(|chunk| chunk.iter_mut().for_each(|v| *v = v.clamp(-1.0, 1.0)));
    out
}

/// A copy of `m` with every row scaled to unit L2 norm; all-zero rows stay zero.
///
/// The norm is accumulated in `f64` so that large finite entries (whose squares overflow
/// `f32`) still normalise correctly.
pub fn l2_normalized_rows(m: &Matrix) -> Matrix {
    let mut out = m.clone();
    let cols = m.cols().max(1);
    out.as_mut_slice().par_chunks_mut(cols).for_each(|row| {
        let norm = row
            .iter()
            .map(|&v| f64::from(v) * f64::from(v))
            .sum::<f64>()
            .sqrt();
        if norm > 0.0 && norm.is_finite() {
            let inv = 1.0 / norm;
            row.iter_mut()
                .for_each(|v| *v = (f64::from(*v) * inv) as f32);
        } else if norm > 0.0 {
            // Squares overflowed f64 (impossible for finite f32 input, kept for safety): scale
            // by the largest magnitude first.
            let max = row.iter().fold(0.0f64, |a, &v| a.max(f64::from(v).abs()));
            let n2 = row
                .iter()
                .map(|&v| (f64::from(v) / max).powi(2))
                .sum::<f64>()
                .sqrt();
            row.iter_mut()
                .for_each(|v| *v = (f64::from(*v) / max / n2) as f32);
        }
    });
    out
}

/// `out = a · bᵀ` for row-major `a` (M x K), `b` (N x K), `out` (M x N), via one `gemm` call
/// parallel over the current rayon pool.
#[allow(unsafe_code)]
fn matmul_abt(a: &Matrix, b: &Matrix, out: &mut Matrix) {
    let (m, k, n) = (a.rows(), a.cols(), b.rows());
    assert!(
        b.cols() == k && out.rows() == m && out.cols() == n,
        "matmul_abt shapes are checked by the caller"
    );
    let to_isize = |x: usize| isize::try_from(x).expect("matrix dimensions fit in isize");
    // SAFETY: the pointers come from live slices of exactly `m*k`, `n*k` and `m*n` elements
    // (Matrix invariant `data.len() == rows * cols`, shapes asserted above). With the strides
    // below every accessed index is in bounds: lhs (i, l) -> i*k + l, rhs (l, j) -> j*k + l
    // (that is bᵀ), dst (i, j) -> i*n + j. `dst` does not alias the inputs (it is borrowed
    // mutably while they are borrowed shared). `read_dst = false`, so `dst = 1·a·bᵀ`.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            out.as_mut_slice().as_mut_ptr(),
            1,
            to_isize(n),
            false,
            a.as_slice().as_ptr(),
            1,
            to_isize(k),
            b.as_slice().as_ptr(),
            to_isize(k),
            1,
            0.0f32,
            1.0f32,
            false,
            false,
            false,
            gemm::Parallelism::Rayon(0),
        );
    }
}

/// Column normalisation of Eq. 2: `ĉ_ij = c_ij / mean_i(c_ij)`, returned as a new matrix.
///
/// A column whose mean is `<= 1e-12` ([`MIN_COLUMN_MEAN`]: zero or negative average similarity)
/// becomes all zeros, i.e. unusable for the solver. Fails on an empty or non-finite matrix.
pub fn normalize_columns(c: &Matrix) -> Result<Matrix> {
    let mut out = c.clone();
    normalize_columns_in_place(&mut out)?;
    Ok(out)
}

/// In-place variant of [`normalize_columns`] (same rules, no extra Q x D allocation).
pub fn normalize_columns_in_place(c: &mut Matrix) -> Result<()> {
    let means = column_means(c)?;
    scale_columns(c, &means);
    Ok(())
}

/// How the columns of `C` are normalised before the graph.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Normalization {
    /// Raw cosine similarities.
    None,
    /// Eq. 2 exactly: `ĉ_ij = c_ij / mean_i(c_ij)` ([`normalize_columns`]).
    Columns,
    /// Eq. 2 with the column mean floored at [`MEAN_FLOOR_FRACTION`] of the median column mean
    /// ([`normalize_columns_floored`]). The default.
    #[default]
    FlooredColumns,
}

impl Normalization {
    /// Applies this normalisation to a copy of `c`.
    pub fn apply(self, c: &Matrix) -> Result<Matrix> {
        match self {
            Normalization::None => {
                c.check_finite("similarity matrix")?;
                Ok(c.clone())
            }
            Normalization::Columns => normalize_columns(c),
            Normalization::FlooredColumns => normalize_columns_floored(c),
        }
    }
}

/// The fraction of the median column mean below which [`normalize_columns_floored`] stops
/// dividing by a column's own mean.
pub const MEAN_FLOOR_FRACTION: f64 = 0.5;

/// Eq. 2 with a floor on the denominator: `ĉ_ij = c_ij / max(mean_i(c_ij), f · median_k mean_i(c_ik))`
/// with `f` = [`MEAN_FLOOR_FRACTION`].
///
/// Why: Eq. 2 is meant to *down-weight* reference images that look like everything (sky,
/// road). Its side effect is to *up-weight* reference images that look like nothing: a dark
/// tunnel frame has a tiny column mean, so dividing by it turns noise into the largest `ĉ` of
/// the matrix, and a route parks on that column (spec §7; on the Nordland dev split with HOG
/// the path parks on one tunnel frame for 170 queries). Flooring the mean keeps Eq. 2 exactly
/// for every column whose mean is at least half the median, and stops the amplification for the
/// rest. On the dev split the floor fraction can be anywhere in 0.25-1.0 with the same result
/// (AP 0.845-0.850), so the constant is not tuned to it. Fails like [`normalize_columns`].
pub fn normalize_columns_floored(c: &Matrix) -> Result<Matrix> {
    let mut out = c.clone();
    let mut means = column_means(&out)?;
    let mut sorted: Vec<f64> = means
        .iter()
        .copied()
        .filter(|m| *m > MIN_COLUMN_MEAN)
        .collect();
    if !sorted.is_empty() {
        let mid = sorted.len() / 2;
        let (_, median, _) = sorted.select_nth_unstable_by(mid, f64::total_cmp);
        let floor = MEAN_FLOOR_FRACTION * *median;
        means.iter_mut().for_each(|m| *m = m.max(floor));
    }
    scale_columns(&mut out, &means);
    Ok(out)
}

/// Column means of `c` in `f64`; fails on an empty or non-finite matrix.
fn column_means(c: &Matrix) -> Result<Vec<f64>> {
    if c.rows() == 0 || c.cols() == 0 {
        return Err(Error::Empty(format!(
            "similarity matrix is {}x{}",
            c.rows(),
            c.cols()
        )));
    }
    c.check_finite("similarity matrix")?;
    let cols = c.cols();
    // Column sums in f64, accumulated per block of rows in parallel, then reduced.
    let sums = c
        .as_slice()
        .par_chunks(cols * 64)
        .map(|block| {
            let mut s = vec![0.0f64; cols];
            for row in block.chunks_exact(cols) {
                s.iter_mut().zip(row).for_each(|(a, &v)| *a += f64::from(v));
            }
            s
        })
        .reduce(
            || vec![0.0f64; cols],
            |mut a, b| {
                a.iter_mut().zip(&b).for_each(|(x, y)| *x += y);
                a
            },
        );
    let rows = c.rows() as f64;
    Ok(sums.iter().map(|s| s / rows).collect())
}

/// Divides each column by its mean; columns with a mean `<= MIN_COLUMN_MEAN` become zeros.
fn scale_columns(c: &mut Matrix, means: &[f64]) {
    let scale: Vec<f64> = means
        .iter()
        .map(|&mean| {
            if mean > MIN_COLUMN_MEAN {
                1.0 / mean
            } else {
                0.0
            }
        })
        .collect();
    let cols = c.cols();
    c.as_mut_slice().par_chunks_mut(cols).for_each(|row| {
        row.iter_mut()
            .zip(&scale)
            .for_each(|(v, &s)| *v = (f64::from(*v) * s) as f32);
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn floored_normalisation_keeps_eq2_above_the_floor_and_caps_tiny_columns() {
        // Column means: 1.0, 0.8, 0.6, 0.05 -> median of (0.05, 0.6, 0.8, 1.0) is 0.8 (upper
        // middle); floor 0.4. Columns 0-2 are Eq. 2 exactly, column 3 is divided by 0.4.
        let c = Matrix::from_vec(2, 4, vec![1.2, 0.8, 0.7, 0.08, 0.8, 0.8, 0.5, 0.02]).unwrap();
        let exact = normalize_columns(&c).unwrap();
        let floored = normalize_columns_floored(&c).unwrap();
        for i in 0..2 {
            for j in 0..3 {
                assert!((exact.get(i, j) - floored.get(i, j)).abs() < 1e-6);
            }
        }
        assert!((floored.get(0, 3) - 0.08 / 0.4).abs() < 1e-6, "{floored:?}");
        assert!((exact.get(0, 3) - 0.08 / 0.05).abs() < 1e-5, "{exact:?}");
    }

    #[test]
    fn normalisation_kinds_dispatch() {
        let c = Matrix::from_vec(2, 2, vec![1.0, 0.5, 3.0, 0.5]).unwrap();
        assert_eq!(Normalization::None.apply(&c).unwrap(), c);
        assert_eq!(
            Normalization::Columns.apply(&c).unwrap(),
            normalize_columns(&c).unwrap()
        );
        assert_eq!(
            Normalization::FlooredColumns.apply(&c).unwrap(),
            normalize_columns_floored(&c).unwrap()
        );
        let bad = Matrix::from_vec(1, 1, vec![f32::NAN]).unwrap();
        assert!(Normalization::None.apply(&bad).is_err());
    }

    #[test]
    fn cosine_against_normalized_references_is_bit_identical() {
        let m = |rows: usize, cols: usize, seed: usize| {
            let data = (0..rows * cols)
                .map(|k| ((k * 37 + seed * 11) % 101) as f32 / 25.0 - 0.7)
                .collect();
            Matrix::from_vec(rows, cols, data).unwrap()
        };
        for (q, d, n) in [(1, 7, 3), (3, 5000, 64), (10, 2400, 33)] {
            let (queries, mut refs) = (m(q, n, 1), m(d, n, 2));
            refs.row_mut(d / 2).fill(0.0); // a zero descriptor
            let normalized = l2_normalized_rows(&refs);
            assert_eq!(
                cosine_matrix_normalized(&queries, &normalized).unwrap(),
                cosine_matrix(&queries, &refs).unwrap()
            );
        }
        let refs = l2_normalized_rows(&m(4, 3, 0));
        assert!(cosine_matrix_normalized(&m(2, 4, 0), &refs).is_err());
        assert!(cosine_matrix_normalized(&Matrix::zeros(0, 3), &refs).is_err());
        let bad = Matrix::from_vec(1, 3, vec![0.0, f32::NAN, 1.0]).unwrap();
        assert!(cosine_matrix_normalized(&bad, &refs).is_err());
    }

    fn naive_cosine(q: &Matrix, d: &Matrix) -> Vec<f64> {
        let mut out = Vec::new();
        for i in 0..q.rows() {
            for j in 0..d.rows() {
                let (mut dot, mut nq, mut nd) = (0.0f64, 0.0f64, 0.0f64);
                for k in 0..q.cols() {
                    let (a, b) = (f64::from(q.get(i, k)), f64::from(d.get(j, k)));
                    dot += a * b;
                    nq += a * a;
                    nd += b * b;
                }
                out.push(if nq == 0.0 || nd == 0.0 {
                    0.0
                } else {
                    dot / (nq.sqrt() * nd.sqrt())
                });
            }
        }
        out
    }

    fn matrix_strategy(rows: usize, cols: usize) -> impl Strategy<Value = Matrix> {
        proptest::collection::vec(-5.0f32..5.0, rows * cols)
            .prop_map(move |v| Matrix::from_vec(rows, cols, v).expect("length matches"))
    }

    proptest! {
        #[test]
        fn cosine_equals_naive_triple_loop(
            (q, d) in (1usize..7, 1usize..9, 1usize..13).prop_flat_map(|(qr, dr, n)| {
                (matrix_strategy(qr, n), matrix_strategy(dr, n))
            })
        ) {
            let c = cosine_matrix(&q, &d).unwrap();
            prop_assert_eq!((c.rows(), c.cols()), (q.rows(), d.rows()));
            for (got, want) in c.as_slice().iter().zip(naive_cosine(&q, &d)) {
                prop_assert!((f64::from(*got) - want).abs() < 1e-5, "{} vs {}", got, want);
                prop_assert!((-1.0..=1.0).contains(got));
            }
        }

        #[test]
        fn normalized_columns_have_mean_one(c in matrix_strategy(5, 4).prop_map(|m| {
            // Shift into positive similarities so every column mean is > 0.
            let v = m.as_slice().iter().map(|x| x.abs() + 0.1).collect();
            Matrix::from_vec(5, 4, v).unwrap()
        })) {
            let n = normalize_columns(&c).unwrap();
            for j in 0..4 {
                let mean: f64 = (0..5).map(|i| f64::from(n.get(i, j))).sum::<f64>() / 5.0;
                prop_assert!((mean - 1.0).abs() < 1e-5, "column {} mean {}", j, mean);
            }
        }
    }

    #[test]
    fn cosine_large_enough_to_use_parallel_gemm_matches_naive() {
        // Shapes above gemm's threading threshold and not multiples of its block sizes.
        let (qr, dr, n) = (70, 53, 131);
        let gen = |r: usize, seed: u32| {
            let v = (0..r * n)
                .map(|k| ((k as u32).wrapping_mul(2654435761).wrapping_add(seed) % 1000) as f32)
                .map(|x| x / 500.0 - 1.0)
                .collect();
            Matrix::from_vec(r, n, v).unwrap()
        };
        let (q, d) = (gen(qr, 7), gen(dr, 99));
        let c = cosine_matrix(&q, &d).unwrap();
        for (got, want) in c.as_slice().iter().zip(naive_cosine(&q, &d)) {
            assert!((f64::from(*got) - want).abs() < 1e-5, "{got} vs {want}");
        }
    }

    #[test]
    fn identical_rows_give_one_and_zero_rows_give_zero() {
        let q = Matrix::from_rows(&[vec![3.0, 4.0], vec![0.0, 0.0]]).unwrap();
        let d = Matrix::from_rows(&[vec![6.0, 8.0], vec![-3.0, -4.0], vec![0.0, 0.0]]).unwrap();
        let c = cosine_matrix(&q, &d).unwrap();
        assert_eq!(c.row(0), &[1.0, -1.0, 0.0]);
        assert_eq!(c.row(1), &[0.0, 0.0, 0.0]);
    }

    #[test]
    fn huge_finite_values_still_normalise() {
        let q = Matrix::from_rows(&[vec![3e30f32, 4e30]]).unwrap();
        let d = Matrix::from_rows(&[vec![3.0f32, 4.0]]).unwrap();
        let c = cosine_matrix(&q, &d).unwrap();
        assert!((c.get(0, 0) - 1.0).abs() < 1e-6);
    }

    #[test]
    fn cosine_rejects_bad_input() {
        let a = Matrix::from_rows(&[vec![1.0, 2.0]]).unwrap();
        let b = Matrix::from_rows(&[vec![1.0, 2.0, 3.0]]).unwrap();
        let err = cosine_matrix(&a, &b).unwrap_err();
        assert!(matches!(err, Error::Shape(_)), "{err}");
        assert!(err.to_string().contains("length 2") && err.to_string().contains("length 3"));

        let empty = Matrix::zeros(0, 2);
        assert!(matches!(cosine_matrix(&empty, &a), Err(Error::Empty(_))));
        assert!(matches!(cosine_matrix(&a, &empty), Err(Error::Empty(_))));
        let no_cols = Matrix::zeros(2, 0);
        assert!(matches!(
            cosine_matrix(&no_cols, &no_cols),
            Err(Error::Empty(_))
        ));

        let nan = Matrix::from_rows(&[vec![1.0, f32::NAN]]).unwrap();
        match cosine_matrix(&a, &nan) {
            Err(Error::NonFinite { what, row, col, .. }) => {
                assert_eq!((what, row, col), ("reference descriptors", 0, 1));
            }
            other => panic!("expected NonFinite, got {other:?}"),
        }
    }

    #[test]
    fn normalize_columns_divides_by_column_mean_and_zeroes_unusable_columns() {
        let c = Matrix::from_rows(&[vec![0.2, 0.0, -0.5, 1.0], vec![0.6, 0.0, 0.1, 3.0]]).unwrap();
        let n = normalize_columns(&c).unwrap();
        // Column 0: mean 0.4; column 1: mean 0 -> zeros; column 2: mean -0.2 -> zeros.
        assert!((n.get(0, 0) - 0.5).abs() < 1e-6 && (n.get(1, 0) - 1.5).abs() < 1e-6);
        assert_eq!((n.get(0, 1), n.get(1, 1)), (0.0, 0.0));
        assert_eq!((n.get(0, 2), n.get(1, 2)), (0.0, 0.0));
        assert!((n.get(0, 3) - 0.5).abs() < 1e-6 && (n.get(1, 3) - 1.5).abs() < 1e-6);

        let mut in_place = c.clone();
        normalize_columns_in_place(&mut in_place).unwrap();
        assert_eq!(in_place, n);
    }

    #[test]
    fn normalize_columns_spans_several_parallel_blocks() {
        // 200 rows > one 64-row reduction block: the parallel reduction must add all blocks.
        let rows: Vec<Vec<f32>> = (0..200).map(|i| vec![i as f32 + 1.0, 2.0]).collect();
        let n = normalize_columns(&Matrix::from_rows(&rows).unwrap()).unwrap();
        let mean0: f64 = (0..200).map(|i| f64::from(n.get(i, 0))).sum::<f64>() / 200.0;
        assert!((mean0 - 1.0).abs() < 1e-6, "{mean0}");
        assert!((0..200).all(|i| n.get(i, 1) == 1.0));
    }

    #[test]
    fn normalize_columns_rejects_empty_and_non_finite() {
        assert!(matches!(
            normalize_columns(&Matrix::zeros(0, 3)),
            Err(Error::Empty(_))
        ));
        let bad = Matrix::from_rows(&[vec![1.0, f32::INFINITY]]).unwrap();
        assert!(matches!(
            normalize_columns(&bad),
            Err(Error::NonFinite { row: 0, col: 1, .. })
        ));
    }
}
