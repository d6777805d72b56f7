//! Histogram-of-oriented-gradients global descriptor (Dalal & Triggs 2005; the flow paper,
//! Section III-A, computes it on a dense grid of 32 px cells over the whole 1024x768 image).
//!
//! Layout, as OpenCV's `HOGDescriptor` with one window covering the whole image:
//!
//! * the image is converted to 8-bit luma (Rec. 709 weights, as `image`'s `to_luma8`) and, when
//!   [`HogOptions::resize`] asks for it, resized with a triangle (bilinear) filter, both by the
//!   shared preparation path ([`super::prepare_gray`]). HOG reads gray only
//!   ([`Extractor::pixels`]), so callers that decode for it get a YCbCr JPEG's Y plane (BT.601
//!   luma, decoded without its chroma: [`super::Pixels::Gray`]) and the conversion is a no-op;
//! * gradients are centred `[-1, 0, 1]` differences in x and y, with replicated border pixels;
//!   the magnitude is `sqrt(gx² + gy²)`, the orientation is unsigned (`0..180°`, `gy` pointing
//!   down the image);
//! * [`BINS`] = 9 orientation bins whose centres are `0°, 20°, ..., 160°`; bin 0 holds horizontal
//!   gradients (vertical edges), and a pixel's magnitude is split linearly between the two bins
//!   nearest to its orientation (wrapping from 160° back to 0°). There is no spatial interpolation
//!   between cells: every pixel votes into its own cell only;
//! * square cells of `cell_size` px; blocks of 2x2 cells with a stride of one cell; each block is
//!   L2-Hys normalised (`v / (‖v‖ + 0.1·len)`, clip at 0.2, `v / (‖v‖ + 1e-3)`, the constants of
//!   OpenCV), so an all-flat block yields zeros and never NaN;
//! * the descriptor concatenates the blocks row by row (top to bottom, left to right); inside a
//!   block its cells are row-major too, 9 bins each.
//!
//! Borders: the grid has `floor(W/C) x floor(H/C)` cells and is centred in the image; the
//! leftover margin (fewer than `C` px per axis) is split evenly, the left/top part getting the
//! smaller half, and its pixels only serve as neighbours for the gradients. An axis with exactly
//! one cell gets blocks that span that single cell. An image smaller than one cell on either axis
//! is an [`Error::Image`]. The descriptor length therefore depends only on the spec and the image
//! size ([`Extractor::dim_for`]): 64x32 with 8 px cells gives 7·3·36 = 756 values, 1024x768 with
//! 32 px cells 31·23·36 = 25,668.
//!
//! Speed: one pass over the grid rows with `f32` row buffers; the orientation comes from a
//! polynomial arctangent (error below 1e-5 rad) instead of `atan2`, so the per-row gradient,
//! magnitude and orientation loops have no branches and vectorise; only the histogram votes are
//! scalar.

use std::f32::consts::{FRAC_PI_2, PI};

use image::{DynamicImage, GrayImage};

use super::Extractor;
use crate::{Error, Result};

/// Number of orientation bins per cell.
pub const BINS: usize = 9;
/// Smallest accepted cell side in pixels.
pub const MIN_CELL_SIZE: u32 = 2;
/// Largest accepted cell side in pixels.
pub const MAX_CELL_SIZE: u32 = 512;
/// Largest accepted side of [`HogOptions::resize`] in pixels.
pub const MAX_RESIZE_SIDE: u32 = 16_384;

/// Per-cell histogram stride: the 9 bins plus one slot that collects the votes of orientations
/// between 160° and 180° for bin 0, folded in after the pass (keeps the vote loop branch-free).
const STRIDE: usize = BINS + 1;
/// L2-Hys clipping threshold.
const CLIP: f32 = 0.2;

/// User-facing HOG settings; validate them with [`HogSpec::new`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HogOptions {
    /// Side of a square cell in pixels (default 32, the paper's).
    pub cell_size: u32,
    /// Optional resize to `(width, height)` before extraction.
    pub resize: Option<(u32, u32)>,
}

impl Default for HogOptions {
    fn default() -> Self {
        HogOptions {
            cell_size: 32,
            resize: None,
        }
    }
}

/// Validated HOG settings; implements [`Extractor`].
#[derive(Clone, Debug, PartialEq)]
pub struct HogSpec {
    options: HogOptions,
}

/// The cell grid of one image size (see the module doc, "Borders").
#[derive(Clone, Copy, Debug, PartialEq)]
struct Grid {
    cell: usize,
    cells_x: usize,
    cells_y: usize,
    /// Top-left pixel of the grid.
    x0: usize,
    y0: usize,
    /// Cells per block on each axis: 2, or 1 when the axis has a single cell.
    block_x: usize,
    block_y: usize,
}

impl Grid {
    fn blocks_x(&self) -> usize {
        self.cells_x + 1 - self.block_x
    }

    fn blocks_y(&self) -> usize {
        self.cells_y + 1 - self.block_y
    }

    fn block_len(&self) -> usize {
        self.block_x * self.block_y * BINS
    }

    fn dim(&self) -> usize {
        self.blocks_x() * self.blocks_y() * self.block_len()
    }
}

impl HogSpec {
    /// Validates `options`: `cell_size` within [`MIN_CELL_SIZE`]..=[`MAX_CELL_SIZE`], and a
    /// resize, if any, with both sides within `cell_size..=`[`MAX_RESIZE_SIDE`].
    pub fn new(options: HogOptions) -> Result<Self> {
        let c = options.cell_size;
        if !(MIN_CELL_SIZE..=MAX_CELL_SIZE).contains(&c) {
            return Err(Error::param(
                "cell_size",
                format!("must be between {MIN_CELL_SIZE} and {MAX_CELL_SIZE} px, got {c}"),
            ));
        }
        if let Some((w, h)) = options.resize {
            let side = MIN_CELL_SIZE..=MAX_RESIZE_SIDE;
            if !side.contains(&w) || !side.contains(&h) {
                return Err(Error::param(
                    "resize",
                    format!(
                        "both sides must be between {MIN_CELL_SIZE} and {MAX_RESIZE_SIDE} px, \
                         got {w}x{h}"
                    ),
                ));
            }
            if w < c || h < c {
                return Err(Error::inconsistent(
                    "resize",
                    format!("both sides must be at least the cell size ({c} px), got {w}x{h}"),
                ));
            }
        }
        Ok(HogSpec { options })
    }

    /// The validated options.
    pub fn options(&self) -> HogOptions {
        self.options
    }

    /// The grid for an image of `width x height` px *after* any resize.
    fn grid(&self, width: u32, height: u32) -> Result<Grid> {
        let c = self.options.cell_size;
        if width < c || height < c {
            return Err(Error::Image {
                name: "input".into(),
                reason: format!("{width}x{height} px is smaller than one HOG cell of {c}x{c} px"),
            });
        }
        let (w, h, c) = (width as usize, height as usize, c as usize);
        let (cells_x, cells_y) = (w / c, h / c);
        Ok(Grid {
            cell: c,
            cells_x,
            cells_y,
            x0: (w - cells_x * c) / 2,
            y0: (h - cells_y * c) / 2,
            block_x: cells_x.min(2),
            block_y: cells_y.min(2),
        })
    }

    /// The HOG of a grayscale image as is (no resize; that happens in [`Extractor::extract`]).
    fn compute(&self, gray: &GrayImage) -> Result<Vec<f32>> {
        let grid = self.grid(gray.width(), gray.height())?;
        let hist = cell_histograms(gray, &grid);
        Ok(normalised_blocks(&hist, &grid))
    }
}

impl Extractor for HogSpec {
    fn dim_for(&self, width: u32, height: u32) -> Result<usize> {
        if width == 0 || height == 0 {
            return Err(Error::Image {
                name: "input".into(),
                reason: format!("{width}x{height} px has no pixels"),
            });
        }
        if let Some((w, h)) = self.options.resize {
            // An image with less than one cell of detail is not brought to the geometry: its
            // upscaled gradients would describe nothing (features::geometry).
            let c = self.options.cell_size;
            if width < c || height < c {
                return Err(Error::Image {
                    name: "input".into(),
                    reason: format!(
                        "{width}x{height} px is smaller than one HOG cell of {c}x{c} px, too \
                         small to bring to the input geometry {w}x{h}"
                    ),
                });
            }
            return Ok(self.grid(w, h)?.dim());
        }
        Ok(self.grid(width, height)?.dim())
    }

    fn extract(&self, image: &DynamicImage) -> Result<Vec<f32>> {
        // Fail on unusable sizes before spending time on conversion and resizing.
        self.dim_for(image.width(), image.height())?;
        self.compute(&*super::prepare_gray(image, self.options.resize)?)
    }

    fn pixels(&self) -> super::Pixels {
        super::Pixels::Gray
    }
}

/// Unsigned gradient orientation of `(gx, gy)` in bin units, within `[0, BINS)`.
///
/// Branch-free (selects only) so that the caller's loop vectorises; `atan` is a minimax
/// polynomial on `[0, 1]` with an absolute error below 1e-5 rad.
#[inline(always)]
fn orientation_bins(gx: f32, gy: f32) -> f32 {
    // Fold onto the upper half-plane: orientations are taken modulo 180°.
    let flip = gy < 0.0;
    let gx = if flip { -gx } else { gx };
    let gy = if flip { -gy } else { gy };
    let ax = gx.abs();
    let hi = ax.max(gy);
    let lo = ax.min(gy);
    // `hi == 0` only for a zero gradient, whose magnitude (and so vote) is zero anyway.
    let a = lo / hi.max(f32::MIN_POSITIVE);
    let s = a * a;
    let mut r = ((-0.046_496_475 * s + 0.159_314_22) * s - 0.327_622_76) * s * a + a;
    r = if gy > ax { FRAC_PI_2 - r } else { r };
    r = if gx < 0.0 { PI - r } else { r };
    let t = r * (BINS as f32 / PI);
    // 180° is 0°.
    if t >= BINS as f32 {
        t - BINS as f32
    } else {
        t
    }
}

/// The lower of the two bins that share a vote at `t` in `[0, BINS)`: `floor(t)`, or `t - 1`
/// when `t` is a whole number (then the upper bin gets the whole vote, which is the same
/// split). Computed as `round(t - 0.5)` by adding 1.5·2²³, where `f32` spacing is 1, so that
/// it vectorises without the NaN and range checks of an `as` cast.
#[inline(always)]
fn lower_bin(t: f32) -> u32 {
    const MAGIC: f32 = 12_582_912.0; // 1.5 * 2^23
    let rounded = (t - 0.5) + MAGIC;
    let k = rounded.to_bits() as i32 - MAGIC.to_bits() as i32;
    k.clamp(0, BINS as i32 - 1) as u32
}

/// Per-cell orientation histograms, `cells_y x cells_x x STRIDE`, wrap slot folded into bin 0.
fn cell_histograms(gray: &GrayImage, g: &Grid) -> Vec<f32> {
    let width = gray.width() as usize;
    let height = gray.height() as usize;
    let pixels: &[u8] = gray.as_raw();
    let c = g.cell;
    let gw = g.cells_x * c;
    let (x0, x1) = (g.x0, g.x0 + gw);
    let mut hist = vec![0f32; g.cells_y * g.cells_x * STRIDE];
    // `row` holds the current row from x0-1 to x1 (replicated at the image border).
    let mut row = vec![0f32; gw + 2];
    // Per pixel: lower bin, and the magnitude's shares for that bin and the next one.
    let mut bin = vec![0u32; gw];
    let mut lower = vec![0f32; gw];
    let mut upper = vec![0f32; gw];
    for (cy, hrow) in hist.chunks_exact_mut(g.cells_x * STRIDE).enumerate() {
        for y in g.y0 + cy * c..g.y0 + (cy + 1) * c {
            let line = |yy: usize| &pixels[yy * width..(yy + 1) * width];
            let up = line(y.saturating_sub(1));
            let cur = line(y);
            let down = line((y + 1).min(height - 1));
            row[0] = f32::from(cur[x0.saturating_sub(1)]);
            row[gw + 1] = f32::from(cur[x1.min(width - 1)]);
            for (r, &p) in row[1..=gw].iter_mut().zip(&cur[x0..x1]) {
                *r = f32::from(p);
            }
            // Branch-free and without indexing, so that it vectorises.
            let gradients = row[2..]
                .iter()
                .zip(&row[..gw])
                .zip(up[x0..x1].iter().zip(&down[x0..x1]));
            let outputs = bin.iter_mut().zip(lower.iter_mut().zip(upper.iter_mut()));
            for ((k, (lo, hi)), ((&right, &left), (&u, &d))) in outputs.zip(gradients) {
                let gx = right - left;
                let gy = f32::from(d) - f32::from(u);
                let m = (gx * gx + gy * gy).sqrt();
                let t = orientation_bins(gx, gy);
                let floor = lower_bin(t);
                *k = floor;
                *hi = m * (t - floor as f32);
                *lo = m - *hi;
            }
            for (h, ((ks, los), his)) in hrow.chunks_exact_mut(STRIDE).zip(
                bin.chunks_exact(c)
                    .zip(lower.chunks_exact(c))
                    .zip(upper.chunks_exact(c)),
            ) {
                vote(h, ks, los, his);
            }
        }
    }
    for h in hist.chunks_exact_mut(STRIDE) {
        h[0] += h[BINS];
    }
    hist
}

/// Adds one cell row's votes to the cell histogram `h` (`STRIDE` long). The lower and upper
/// shares go to separate accumulators indexed by the same lower bin, and even and odd pixels
/// to separate copies: consecutive pixels then never read back a partially overlapping store
/// (which stalls store-to-load forwarding), and the dependency chains are halved.
#[inline]
fn vote(h: &mut [f32], bins: &[u32], lower: &[f32], upper: &[f32]) {
    let (mut lo0, mut hi0, mut lo1, mut hi1) =
        ([0f32; BINS], [0f32; BINS], [0f32; BINS], [0f32; BINS]);
    let pairs = bins
        .chunks_exact(2)
        .zip(lower.chunks_exact(2).zip(upper.chunks_exact(2)));
    for (k, (lo, hi)) in pairs {
        let (k0, k1) = ((k[0] as usize).min(BINS - 1), (k[1] as usize).min(BINS - 1));
        lo0[k0] += lo[0];
        hi0[k0] += hi[0];
        lo1[k1] += lo[1];
        hi1[k1] += hi[1];
    }
    if bins.len() % 2 == 1 {
        let last = bins.len() - 1;
        let k = (bins[last] as usize).min(BINS - 1);
        lo0[k] += lower[last];
        hi0[k] += upper[last];
    }
    for k in 0..BINS {
        h[k] += lo0[k] + lo1[k];
        h[k + 1] += hi0[k] + hi1[k];
    }
}

/// Concatenates the L2-Hys normalised blocks (see the module doc for the order).
fn normalised_blocks(hist: &[f32], g: &Grid) -> Vec<f32> {
    let mut out = Vec::with_capacity(g.dim());
    for by in 0..g.blocks_y() {
        for bx in 0..g.blocks_x() {
            let start = out.len();
            for cy in by..by + g.block_y {
                for cx in bx..bx + g.block_x {
                    let at = (cy * g.cells_x + cx) * STRIDE;
                    out.extend_from_slice(&hist[at..at + BINS]);
                }
            }
            l2_hys(&mut out[start..]);
        }
    }
    out
}

/// L2-Hys in place: L2-normalise, clip at [`CLIP`], renormalise. Zeros stay zeros.
fn l2_hys(block: &mut [f32]) {
    let norm = |v: &[f32]| v.iter().map(|x| x * x).sum::<f32>().sqrt();
    let scale = 1.0 / (norm(block) + 0.1 * block.len() as f32);
    for v in block.iter_mut() {
        *v = (*v * scale).min(CLIP);
    }
    let scale = 1.0 / (norm(block) + 1e-3);
    for v in block.iter_mut() {
        *v *= scale;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{Luma, Rgb, RgbImage};
    use proptest::prelude::*;

    fn spec(cell: u32) -> HogSpec {
        HogSpec::new(HogOptions {
            cell_size: cell,
            resize: None,
        })
        .unwrap()
    }

    fn gray(w: u32, h: u32, f: impl Fn(u32, u32) -> u8) -> DynamicImage {
        DynamicImage::ImageLuma8(GrayImage::from_fn(w, h, |x, y| Luma([f(x, y)])))
    }

    fn noise(x: u32, y: u32) -> u8 {
        (x.wrapping_mul(2_654_435_761) ^ y.wrapping_mul(40_503)).wrapping_mul(97) as u8
    }

    /// Straightforward HOG with `atan2`, per-pixel clamped neighbours and per-cell loops.
    fn reference(img: &GrayImage, cell: usize) -> Vec<f32> {
        let (w, h) = (img.width() as i64, img.height() as i64);
        let px = |x: i64, y: i64| {
            f32::from(img.get_pixel(x.clamp(0, w - 1) as u32, y.clamp(0, h - 1) as u32)[0])
        };
        let (nx, ny) = (w as usize / cell, h as usize / cell);
        let (x0, y0) = ((w as usize - nx * cell) / 2, (h as usize - ny * cell) / 2);
        let mut hist = vec![[0f32; BINS]; nx * ny];
        for cy in 0..ny {
            for cx in 0..nx {
                for y in y0 + cy * cell..y0 + (cy + 1) * cell {
                    for x in x0 + cx * cell..x0 + (cx + 1) * cell {
                        let (x, y) = (x as i64, y as i64);
                        let gx = px(x + 1, y) - px(x - 1, y);
                        let gy = px(x, y + 1) - px(x, y - 1);
                        let deg = gy.atan2(gx).to_degrees().rem_euclid(180.0);
                        let t = deg / 20.0;
                        let k = t.floor() as usize % BINS;
                        let frac = t - t.floor();
                        let m = (gx * gx + gy * gy).sqrt();
                        hist[cy * nx + cx][k] += m * (1.0 - frac);
                        hist[cy * nx + cx][(k + 1) % BINS] += m * frac;
                    }
                }
            }
        }
        let (bxn, byn) = (nx.min(2), ny.min(2));
        let mut out = Vec::new();
        for by in 0..=ny - byn {
            for bx in 0..=nx - bxn {
                let mut block = Vec::new();
                for cy in by..by + byn {
                    for cx in bx..bx + bxn {
                        block.extend_from_slice(&hist[cy * nx + cx]);
                    }
                }
                let n = block.iter().map(|v| v * v).sum::<f32>().sqrt() + 0.1 * block.len() as f32;
                block.iter_mut().for_each(|v| *v = (*v / n).min(0.2));
                let n = block.iter().map(|v| v * v).sum::<f32>().sqrt() + 1e-3;
                out.extend(block.iter().map(|v| v / n));
            }
        }
        out
    }

    fn block_norms(d: &[f32], block_len: usize) -> Vec<f32> {
        d.chunks(block_len)
            .map(|b| b.iter().map(|v| v * v).sum::<f32>().sqrt())
            .collect()
    }

    #[test]
    fn dimensions_follow_the_grid() {
        assert_eq!(spec(8).dim_for(64, 32).unwrap(), 756);
        assert_eq!(spec(32).dim_for(1024, 768).unwrap(), 25_668);
        // Leftover margins do not add cells.
        assert_eq!(spec(8).dim_for(71, 39).unwrap(), 756);
        // A single cell on an axis: blocks span that one cell.
        assert_eq!(spec(8).dim_for(40, 8).unwrap(), 4 * 2 * BINS);
        assert_eq!(spec(8).dim_for(8, 15).unwrap(), BINS);
        let resized = HogSpec::new(HogOptions {
            cell_size: 8,
            resize: Some((64, 32)),
        })
        .unwrap();
        assert_eq!(resized.dim_for(1000, 9).unwrap(), 756);
    }

    #[test]
    fn too_small_images_are_image_errors() {
        for (w, h) in [(7, 40), (40, 7), (0, 0)] {
            match spec(8).extract(&gray(w, h, noise)) {
                Err(Error::Image { reason, .. }) => {
                    assert!(reason.contains(&format!("{w}x{h} px")), "{reason}")
                }
                other => panic!("{w}x{h}: expected Image error, got {other:?}"),
            }
        }
        let err = spec(8).dim_for(7, 40).unwrap_err().to_string();
        assert!(err.contains("smaller than one HOG cell of 8x8 px"), "{err}");
    }

    #[test]
    fn options_are_validated() {
        for cell in [0, 1, 513] {
            let err = HogSpec::new(HogOptions {
                cell_size: cell,
                resize: None,
            })
            .unwrap_err();
            assert!(
                matches!(
                    err,
                    Error::InvalidParameter {
                        name: "cell_size",
                        ..
                    }
                ),
                "{err}"
            );
        }
        for resize in [(64, 0), (1, 64), (20_000, 64)] {
            let err = HogSpec::new(HogOptions {
                cell_size: 8,
                resize: Some(resize),
            })
            .unwrap_err();
            assert!(
                matches!(err, Error::InvalidParameter { name: "resize", .. }),
                "{err}"
            );
        }
        // In range alone, but smaller than one cell of this spec.
        let err = HogSpec::new(HogOptions {
            cell_size: 8,
            resize: Some((4, 64)),
        })
        .unwrap_err();
        assert!(
            matches!(err, Error::Inconsistent { name: "resize", .. }),
            "{err}"
        );
        let options = HogOptions {
            cell_size: 16,
            resize: Some((64, 48)),
        };
        assert_eq!(HogSpec::new(options).unwrap().options(), options);
        assert_eq!(
            HogOptions::default(),
            HogOptions {
                cell_size: 32,
                resize: None
            }
        );
    }

    #[test]
    fn uniform_image_gives_zeros() {
        let d = spec(8).extract(&gray(64, 32, |_, _| 137)).unwrap();
        assert_eq!(d.len(), 756);
        assert!(d.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn vertical_edge_votes_only_in_the_horizontal_gradient_bin() {
        let d = spec(8)
            .extract(&gray(64, 32, |x, _| if x < 36 { 20 } else { 220 }))
            .unwrap();
        let energy: Vec<f32> = (0..BINS)
            .map(|b| d.iter().skip(b).step_by(BINS).sum())
            .collect();
        assert!(energy[0] > 1.0, "{energy:?}");
        assert!(energy[1..].iter().all(|&e| e == 0.0), "{energy:?}");
    }

    #[test]
    fn horizontal_edge_votes_around_ninety_degrees() {
        // 90° lies midway between the 80° and 100° bins (4 and 5): an even split.
        let d = spec(8)
            .extract(&gray(64, 32, |_, y| if y < 12 { 220 } else { 20 }))
            .unwrap();
        let energy: Vec<f32> = (0..BINS)
            .map(|b| d.iter().skip(b).step_by(BINS).sum())
            .collect();
        assert!(energy[4] > 1.0, "{energy:?}");
        assert!(
            (energy[4] - energy[5]).abs() < 1e-4 * energy[4],
            "{energy:?}"
        );
        let others: f32 = energy
            .iter()
            .enumerate()
            .filter(|(b, _)| *b != 4 && *b != 5)
            .map(|(_, e)| e)
            .sum();
        assert_eq!(others, 0.0, "{energy:?}");
    }

    #[test]
    fn l2_hys_clips_then_renormalises() {
        let mut block = vec![0f32; 36];
        block[0] = 1000.0;
        block[1] = 100.0;
        l2_hys(&mut block);
        // L2 with eps 3.6: 0.9915 and 0.0991; clip: 0.2 and 0.0991; renormalise.
        let second = 100.0 / ((1000f32.powi(2) + 100f32.powi(2)).sqrt() + 3.6);
        let norm = (0.04 + second * second).sqrt() + 1e-3;
        assert!((block[0] - 0.2 / norm).abs() < 1e-5, "{block:?}");
        assert!((block[1] - second / norm).abs() < 1e-5, "{block:?}");
        assert!(block[2..].iter().all(|&v| v == 0.0));
        let mut zeros = vec![0f32; 36];
        l2_hys(&mut zeros);
        assert!(zeros.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn textured_blocks_have_unit_norm() {
        let d = spec(8).extract(&gray(64, 32, noise)).unwrap();
        for (i, n) in block_norms(&d, 36).into_iter().enumerate() {
            assert!((0.99..=1.0).contains(&n), "block {i} norm {n}");
        }
    }

    #[test]
    fn margins_only_serve_as_gradient_neighbours() {
        // 20x8 with 8 px cells: 2 cells, 2 px margins on both sides (grid x = 2..18).
        let only_margins = gray(20, 8, |x, _| if x == 0 || x == 19 { 255 } else { 0 });
        assert!(spec(8)
            .extract(&only_margins)
            .unwrap()
            .iter()
            .all(|&v| v == 0.0));
        let inside = gray(20, 8, |x, _| if x == 2 { 255 } else { 0 });
        assert!(spec(8).extract(&inside).unwrap().iter().any(|&v| v > 0.0));
    }

    #[test]
    fn lower_bin_is_floor_or_the_whole_number_below() {
        for i in 0..90_000 {
            let t = i as f32 / 10_000.0;
            let k = lower_bin(t) as f32;
            let frac = t - k;
            assert!((0.0..=1.0).contains(&frac), "t {t}: k {k}");
            assert!(
                k == t.floor() || (t.fract() == 0.0 && k == t - 1.0),
                "t {t}: k {k}"
            );
        }
        assert_eq!(lower_bin(8.999_999), 8);
        assert_eq!(lower_bin(0.0), 0);
    }

    #[test]
    fn orientation_polynomial_matches_atan2() {
        for k in 0..3600 {
            let a = (k as f32 / 10.0).to_radians();
            let (gx, gy) = (50.0 * a.cos(), 50.0 * a.sin());
            let want = gy.atan2(gx).to_degrees().rem_euclid(180.0) / 20.0;
            let got = orientation_bins(gx, gy);
            assert!((0.0..BINS as f32).contains(&got), "{k}: {got}");
            let diff = (got - want).abs().min(BINS as f32 - (got - want).abs());
            assert!(
                diff < 1e-3,
                "angle {}°: got {got}, want {want}",
                k as f32 / 10.0
            );
        }
        assert_eq!(orientation_bins(0.0, 0.0), 0.0);
    }

    #[test]
    fn colour_and_resize_happen_inside_extract() {
        let rgb = RgbImage::from_fn(96, 48, |x, y| Rgb([noise(x, y), noise(y, x), 40]));
        let s = spec(8);
        let luma = DynamicImage::ImageRgb8(rgb.clone()).to_luma8();
        assert_eq!(
            s.extract(&DynamicImage::ImageRgb8(rgb.clone())).unwrap(),
            s.extract(&DynamicImage::ImageLuma8(luma.clone())).unwrap()
        );
        let r = HogSpec::new(HogOptions {
            cell_size: 8,
            resize: Some((64, 32)),
        })
        .unwrap();
        let small = crate::features::resize_gray(&luma, 64, 32)
            .unwrap()
            .into_owned();
        assert_eq!(
            r.extract(&DynamicImage::ImageRgb8(rgb)).unwrap(),
            s.extract(&DynamicImage::ImageLuma8(small)).unwrap()
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn length_is_dim_for_and_values_are_finite(
            cell in 2u32..20, w in 1u32..90, h in 1u32..90, seed in 0u32..1000,
        ) {
            let s = spec(cell);
            let img = gray(w, h, |x, y| noise(x + seed, y * 3 + seed));
            if w < cell || h < cell {
                prop_assert!(s.dim_for(w, h).is_err());
                prop_assert!(matches!(s.extract(&img), Err(Error::Image { .. })), "expected an error");
            } else {
                let d = s.extract(&img).unwrap();
                prop_assert_eq!(d.len(), s.dim_for(w, h).unwrap());
                prop_assert!(d.iter().all(|v| v.is_finite()));
            }
        }

        #[test]
        fn fast_path_matches_the_reference(
            cell in 2usize..12, w in 12u32..70, h in 12u32..50, seed in 0u32..1000, flat in 0u32..3,
        ) {
            // `flat` = 0: noise; 1: smooth ramp; 2: blocky (many zero gradients).
            let img = GrayImage::from_fn(w, h, |x, y| Luma([match flat {
                0 => noise(x + seed, y + seed),
                1 => ((x * 3 + y * seed % 7) % 256) as u8,
                _ => if (x / 5 + y / 7 + seed) % 2 == 0 { 30 } else { 200 },
            }]));
            let fast = spec(cell as u32).extract(&DynamicImage::ImageLuma8(img.clone())).unwrap();
            let slow = reference(&img, cell);
            prop_assert_eq!(fast.len(), slow.len());
            for (i, (a, b)) in fast.iter().zip(&slow).enumerate() {
                prop_assert!((a - b).abs() < 2e-3, "value {}: fast {} reference {}", i, a, b);
            }
        }
    }
}
