//! The similarity matrix as a picture: queries as rows (downwards), references as columns,
//! bright where a query looks like a reference. Both papers draw their route hypotheses over
//! this figure; the dashboard does the same over the picture of each localization.
//!
//! The picture is bounded whatever the matrix: at most [`MAX_SIDE`] x [`MAX_SIDE`] grey
//! pixels. Pixel row `r` covers queries `r*Q/R .. (r+1)*Q/R` (integer division; every block is
//! non-empty because `R <= Q`), pixel column `c` likewise for references, so drawing the
//! picture stretched over the plot area `[0, D] x [0, Q]` puts each pixel over the cells it
//! stands for. A pixel is the **maximum** of its block: a route is a thin bright line of
//! single cells, which averaging over a 60-column block of a 30,000-image map would wash out,
//! while the maximum keeps it visible.
//!
//! Grey levels map the 1st percentile of the pixel values to black and the 99.5th to white
//! (clamped), so a few extreme cells (the tunnel frames whose tiny column means inflate `ĉ`)
//! do not turn everything else black; when those percentiles are equal (a thin route on a
//! uniform background) white is the maximum instead. The two values are kept ([`MatrixPicture::lo`],
//! [`MatrixPicture::hi`]) for a legend.

use std::io::Cursor;

use image::codecs::png::PngEncoder;
use image::{ExtendedColorType, ImageEncoder};
use rayon::prelude::*;

use crate::{Error, Matrix, Result};

/// Largest picture side in pixels.
pub const MAX_SIDE: usize = 512;

/// A downsampled grey picture of a similarity matrix (see the module doc).
#[derive(Clone, Debug, PartialEq)]
pub struct MatrixPicture {
    /// Queries (rows) of the matrix.
    pub query_count: usize,
    /// References (columns) of the matrix.
    pub reference_count: usize,
    /// Picture height: `min(query_count, max_rows)`.
    pub rows: usize,
    /// Picture width: `min(reference_count, max_cols)`.
    pub cols: usize,
    /// The matrix value shown black (and below).
    pub lo: f32,
    /// The matrix value shown white (and above).
    pub hi: f32,
    /// Grey levels, row-major, `rows * cols`.
    pub pixels: Vec<u8>,
}

/// The start of block `k` of `n` blocks over `len` items.
#[inline]
fn block_start(k: usize, len: usize, n: usize) -> usize {
    // `k * len` fits: `len` is a matrix side and `k <= n <= MAX_SIDE`-ish.
    (k as u128 * len as u128 / n as u128) as usize
}

impl MatrixPicture {
    /// The picture of `m` (queries x references), at most `max_rows` x `max_cols` pixels.
    /// Errors on an empty matrix or a zero bound; non-finite entries are ignored (a block of
    /// only non-finite entries is black).
    pub fn new(m: &Matrix, max_rows: usize, max_cols: usize) -> Result<Self> {
        let (q, d) = (m.rows(), m.cols());
        if q == 0 || d == 0 {
            return Err(Error::Empty(format!(
                "a similarity matrix picture needs at least one query and one reference, got {q}x{d}"
            )));
        }
        if max_rows == 0 || max_cols == 0 {
            return Err(Error::param(
                "picture size",
                format!("must be at least 1x1, got {max_rows}x{max_cols}"),
            ));
        }
        let rows = q.min(max_rows);
        let cols = d.min(max_cols);
        let col_starts: Vec<usize> = (0..=cols).map(|c| block_start(c, d, cols)).collect();
        let mut pooled = vec![f32::NEG_INFINITY; rows * cols];
        pooled
            .par_chunks_mut(cols)
            .enumerate()
            .for_each(|(r, out)| {
                for i in block_start(r, q, rows)..block_start(r + 1, q, rows) {
                    let row = m.row(i);
                    for (c, o) in out.iter_mut().enumerate() {
                        let block = &row[col_starts[c]..col_starts[c + 1]];
                        let top = block
                            .iter()
                            .copied()
                            .filter(|v| v.is_finite())
                            .fold(f32::NEG_INFINITY, f32::max);
                        *o = o.max(top);
                    }
                }
            });
        let (lo, hi) = grey_range(&pooled);
        let scale = if hi > lo { 255.0 / (hi - lo) } else { 0.0 };
        let pixels = pooled
            .iter()
            .map(|&v| {
                if v.is_finite() {
                    ((v - lo) * scale).round().clamp(0.0, 255.0) as u8
                } else {
                    0
                }
            })
            .collect();
        Ok(MatrixPicture {
            query_count: q,
            reference_count: d,
            rows,
            cols,
            lo,
            hi,
            pixels,
        })
    }

    /// The picture of `m` within [`MAX_SIDE`] x [`MAX_SIDE`].
    pub fn bounded(m: &Matrix) -> Result<Self> {
        Self::new(m, MAX_SIDE, MAX_SIDE)
    }

    /// The pixel `(row, col)` that shows cell `(query, reference)`.
    pub fn pixel_of(&self, query: usize, reference: usize) -> (usize, usize) {
        // Block k covers [k*len/n, (k+1)*len/n): k = the largest with k*len/n <= i.
        let find = |i: usize, len: usize, n: usize| {
            let mut k = (i as u128 * n as u128 / len as u128) as usize;
            while k + 1 < n && block_start(k + 1, len, n) <= i {
                k += 1;
            }
            while k > 0 && block_start(k, len, n) > i {
                k -= 1;
            }
            k
        };
        (
            find(query, self.query_count, self.rows),
            find(reference, self.reference_count, self.cols),
        )
    }

    /// The picture as an 8-bit greyscale PNG.
    pub fn to_png(&self) -> Result<Vec<u8>> {
        let mut out = Vec::new();
        PngEncoder::new(&mut Cursor::new(&mut out))
            .write_image(
                &self.pixels,
                self.cols as u32,
                self.rows as u32,
                ExtendedColorType::L8,
            )
            .map_err(|e| Error::Image {
                name: "similarity picture".into(),
                reason: format!("PNG encoding failed: {e}"),
            })?;
        Ok(out)
    }
}

/// The 1st and 99.5th percentiles of the finite values (`(0, 1)` when there are none).
fn grey_range(values: &[f32]) -> (f32, f32) {
    let mut v: Vec<f32> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return (0.0, 1.0);
    }
    let n = v.len();
    let at = |v: &mut Vec<f32>, p: f64| -> f32 {
        let k = ((p * (n - 1) as f64).round() as usize).min(n - 1);
        *v.select_nth_unstable_by(k, f32::total_cmp).1
    };
    let lo = at(&mut v, 0.01);
    let hi = at(&mut v, 0.995);
    if hi > lo {
        return (lo, hi);
    }
    // Fewer than 0.5 % of the pixels stand out (a thin route on a uniform background): white
    // is then the largest value, so the route still shows.
    let max = v.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    (lo, max)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A Q x D matrix: 0.2 everywhere, 1.0 on the route `j = 3 i` (a vehicle three times
    /// slower than the mapping drive would be `j = i / 3`; any thin line will do).
    fn route(q: usize, d: usize) -> Matrix {
        let mut m = Matrix::zeros(q, d);
        for i in 0..q {
            for j in 0..d {
                m.set(i, j, 0.2);
            }
            if 3 * i < d {
                m.set(i, 3 * i, 1.0);
            }
        }
        m
    }

    #[test]
    fn a_small_matrix_is_drawn_cell_for_cell() {
        let m = route(20, 70);
        let p = MatrixPicture::new(&m, 512, 512).unwrap();
        assert_eq!((p.rows, p.cols), (20, 70));
        assert_eq!((p.lo, p.hi), (0.2, 1.0));
        for i in 0..20 {
            for j in 0..70 {
                let want = if j == 3 * i { 255 } else { 0 };
                assert_eq!(p.pixels[i * 70 + j], want, "({i}, {j})");
                assert_eq!(p.pixel_of(i, j), (i, j));
            }
        }
    }

    #[test]
    fn a_large_matrix_is_bounded_and_keeps_its_route_visible() {
        // 1,000 queries x 30,000 references: 30 M cells into at most 512 x 512 pixels.
        let m = route(1000, 30_000);
        let p = MatrixPicture::bounded(&m).unwrap();
        assert_eq!((p.rows, p.cols), (512, 512));
        assert_eq!(p.pixels.len(), 512 * 512);
        // Every route cell's pixel is white (max pooling), and so is nothing far from it.
        for i in (0..1000).step_by(7) {
            let (r, c) = p.pixel_of(i, 3 * i);
            assert_eq!(p.pixels[r * 512 + c], 255, "query {i}");
        }
        let (r, c) = p.pixel_of(900, 100);
        assert_eq!(p.pixels[r * 512 + c], 0, "off the route is dark");
        let png = p.to_png().unwrap();
        let back = image::load_from_memory(&png).unwrap().to_luma8();
        assert_eq!(back.dimensions(), (512, 512));
        assert_eq!(back.into_raw(), p.pixels);
        assert!(png.len() < 512 * 512, "{} bytes", png.len());
    }

    #[test]
    fn pixel_of_inverts_the_blocks() {
        for (len, n) in [(7, 3), (1000, 512), (30_000, 512), (513, 512), (5, 5)] {
            let mut last = 0;
            for i in 0..len {
                let k = (MatrixPicture {
                    query_count: len,
                    reference_count: 1,
                    rows: n,
                    cols: 1,
                    lo: 0.0,
                    hi: 1.0,
                    pixels: vec![],
                })
                .pixel_of(i, 0)
                .0;
                assert!(block_start(k, len, n) <= i && i < block_start(k + 1, len, n));
                assert!(k >= last && k < n);
                last = k;
            }
            assert_eq!(last, n - 1);
        }
    }

    #[test]
    fn outliers_do_not_wash_out_the_picture() {
        // One huge cell (an inflated tunnel column) among ordinary values 0..1.
        let mut m = Matrix::zeros(50, 50);
        for i in 0..50 {
            for j in 0..50 {
                m.set(i, j, ((i * 50 + j) % 97) as f32 / 97.0);
            }
        }
        m.set(10, 10, 1e6);
        let p = MatrixPicture::new(&m, 512, 512).unwrap();
        assert!(p.hi < 2.0, "hi = {}", p.hi);
        let mid = p.pixels.iter().filter(|&&g| (60..200).contains(&g)).count();
        assert!(mid > 1000, "most cells keep a grey level: {mid}");
        assert_eq!(p.pixels[10 * 50 + 10], 255);
    }

    #[test]
    fn bad_input_is_an_error() {
        assert!(MatrixPicture::new(&Matrix::zeros(0, 5), 10, 10).is_err());
        assert!(MatrixPicture::new(&Matrix::zeros(5, 0), 10, 10).is_err());
        let err = MatrixPicture::new(&Matrix::zeros(5, 5), 0, 10).unwrap_err();
        assert!(err.to_string().contains("picture size"), "{err}");
        // A constant matrix is drawn (black) rather than dividing by zero.
        let p = MatrixPicture::new(&Matrix::zeros(3, 4), 10, 10).unwrap();
        assert!(p.pixels.iter().all(|&g| g == 0));
    }
}
