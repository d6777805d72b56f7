//! The image operations under the detector and the descriptor, on one level of the working
//! image held in the per-thread [`Scratch`]: resampling an image to the working size
//! (bilinear up, area average down), halving a level for the next octave, the separable
//! Gaussian blur and central-difference gradients.
//!
//! Why a module of their own: both the Harris detector and the descriptor's orientation
//! planes smooth and differentiate the same level with these, and they are the only part
//! that knows the planes' layout (row-major `w x h`, borders clamped).

use image::GrayImage;

use super::{sized, Scratch};

/// Pre-smoothing of the working image before gradients, in working pixels.
const SMOOTH_SIGMA: f32 = 1.0;

/// Resamples `image` to `w x h` into `s.level`, intensities in `[0, 1]`: bilinear (pixel
/// centres aligned) when enlarging an axis, area averaging when reducing it. Separable.
pub(super) fn resample(image: &GrayImage, w: usize, h: usize, s: &mut Scratch) {
    let (w0, h0) = (image.width() as usize, image.height() as usize);
    let src = image.as_raw();
    // Horizontal pass: h0 rows of w values.
    let tmp = sized(&mut s.tmp, h0 * w);
    let xs = axis_weights(w0, w);
    for y in 0..h0 {
        let row = &src[y * w0..(y + 1) * w0];
        let out = &mut tmp[y * w..(y + 1) * w];
        for (o, taps) in out.iter_mut().zip(&xs) {
            *o = taps
                .iter()
                .map(|&(i, wt)| f32::from(row[i as usize]) * wt)
                .sum::<f32>()
                / 255.0;
        }
    }
    // Vertical pass.
    let ys = axis_weights(h0, h);
    let level = sized(&mut s.level, w * h);
    for (y, taps) in ys.iter().enumerate() {
        let out = &mut level[y * w..(y + 1) * w];
        out.fill(0.0);
        for &(i, wt) in taps {
            let row = &tmp[i as usize * w..(i as usize + 1) * w];
            for (o, &v) in out.iter_mut().zip(row) {
                *o += wt * v;
            }
        }
    }
}

/// Per output index, the source indices and weights along one axis (`n0 -> n`).
fn axis_weights(n0: usize, n: usize) -> Vec<Vec<(u32, f32)>> {
    let ratio = n0 as f64 / n as f64;
    (0..n)
        .map(|o| {
            if n >= n0 {
                let sx = ((o as f64 + 0.5) * ratio - 0.5).clamp(0.0, (n0 - 1) as f64);
                let i0 = sx.floor() as usize;
                let i1 = (i0 + 1).min(n0 - 1);
                let t = (sx - i0 as f64) as f32;
                if i1 == i0 || t == 0.0 {
                    vec![(i0 as u32, 1.0)]
                } else {
                    vec![(i0 as u32, 1.0 - t), (i1 as u32, t)]
                }
            } else {
                let (a, b) = (o as f64 * ratio, (o as f64 + 1.0) * ratio);
                let mut taps = Vec::new();
                let mut i = a.floor() as usize;
                while (i as f64) < b && i < n0 {
                    let cover = (b.min(i as f64 + 1.0) - a.max(i as f64)) / ratio;
                    if cover > 0.0 {
                        taps.push((i as u32, cover as f32));
                    }
                    i += 1;
                }
                taps
            }
        })
        .collect()
}

/// Halves `s.level` (`w x h`) in place by 2x2 averaging.
pub(super) fn halve(s: &mut Scratch, w: usize, h: usize) {
    let (w2, h2) = (w / 2, h / 2);
    let next = sized(&mut s.next, w2 * h2);
    for y in 0..h2 {
        let (r0, r1) = (&s.level[2 * y * w..], &s.level[(2 * y + 1) * w..]);
        for (x, o) in next[y * w2..(y + 1) * w2].iter_mut().enumerate() {
            *o = 0.25 * (r0[2 * x] + r0[2 * x + 1] + r1[2 * x] + r1[2 * x + 1]);
        }
    }
    std::mem::swap(&mut s.level, &mut s.next);
}

/// Normalised Gaussian taps of radius `ceil(3 sigma)` (at least 1).
fn gaussian(sigma: f32) -> ([f32; 25], usize) {
    let r = ((3.0 * sigma).ceil() as usize).clamp(1, 12);
    let mut k = [0.0f32; 25];
    for (i, v) in k.iter_mut().enumerate().take(2 * r + 1) {
        let d = i as f32 - r as f32;
        *v = (-(d * d) / (2.0 * sigma * sigma)).exp();
    }
    let sum: f32 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= sum);
    (k, r)
}

/// Separable Gaussian blur of `src` into `dst` (`w x h`) with clamped borders, using `tmp` and
/// `padded`. Rows are padded once and columns are accumulated whole rows at a time, so both
/// passes are straight-line loops the compiler vectorises.
pub(super) fn blur(
    src: &[f32],
    dst: &mut [f32],
    tmp: &mut Vec<f32>,
    padded: &mut Vec<f32>,
    w: usize,
    h: usize,
    sigma: f32,
) {
    let (kernel, r) = gaussian(sigma);
    let kernel = &kernel[..2 * r + 1];
    let tmp = sized(tmp, w * h);
    let padded = sized(padded, w + 2 * r);
    for y in 0..h {
        let row = &src[y * w..(y + 1) * w];
        padded[..r].fill(row[0]);
        padded[r..r + w].copy_from_slice(row);
        padded[r + w..].fill(row[w - 1]);
        let out = &mut tmp[y * w..(y + 1) * w];
        out.fill(0.0);
        for (k, &kv) in kernel.iter().enumerate() {
            for (o, &v) in out.iter_mut().zip(&padded[k..k + w]) {
                *o += kv * v;
            }
        }
    }
    for y in 0..h {
        let out = &mut dst[y * w..(y + 1) * w];
        out.fill(0.0);
        for (k, &kv) in kernel.iter().enumerate() {
            let yy = (y + k).saturating_sub(r).min(h - 1);
            for (o, &v) in out.iter_mut().zip(&tmp[yy * w..(yy + 1) * w]) {
                *o += kv * v;
            }
        }
    }
}

/// Smooths `s.level` (`w x h`) by [`SMOOTH_SIGMA`] into `s.smooth` and writes its gradients to
/// `s.gx`, `s.gy`: where both the detector and the descriptor's orientation planes start.
pub(super) fn smoothed_gradients(s: &mut Scratch, w: usize, h: usize) {
    let n = w * h;
    let Scratch {
        level,
        tmp,
        smooth,
        gx,
        gy,
        padded,
        ..
    } = s;
    let smooth = sized(smooth, n);
    blur(&level[..n], smooth, tmp, padded, w, h, SMOOTH_SIGMA);
    let (gx, gy) = (sized(gx, n), sized(gy, n));
    gradients(smooth, gx, gy, w, h);
}

/// Central-difference gradients (one-sided at the borders), per working pixel.
fn gradients(p: &[f32], gx: &mut [f32], gy: &mut [f32], w: usize, h: usize) {
    for y in 0..h {
        let (yu, yd) = (y.saturating_sub(1), (y + 1).min(h - 1));
        let dy = (yd - yu).max(1) as f32;
        let row = &p[y * w..(y + 1) * w];
        let (up, down) = (&p[yu * w..(yu + 1) * w], &p[yd * w..(yd + 1) * w]);
        let (ox, oy) = (&mut gx[y * w..(y + 1) * w], &mut gy[y * w..(y + 1) * w]);
        for x in 0..w {
            oy[x] = (down[x] - up[x]) / dy;
        }
        if w == 1 {
            ox[0] = 0.0;
            continue;
        }
        ox[0] = row[1] - row[0];
        ox[w - 1] = row[w - 1] - row[w - 2];
        for x in 1..w - 1 {
            ox[x] = 0.5 * (row[x + 1] - row[x - 1]);
        }
    }
}
