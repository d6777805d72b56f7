//! The Harris corner detector on one level of the working image: the smoothed gradients'
//! structure tensor, its response `det - k * trace^2`, the thresholds (relative to the
//! level's strongest response, and absolute), non-maximum suppression by a separable window
//! maximum, and one survivor per plateau of equal maxima (the first in raster order).
//!
//! Why apart: detection decides *where* features are, the descriptor *what* they look like;
//! each is tuned and read on its own (its parameters: [`KeypointParams`]'s `harris_k`,
//! `relative_threshold`, `min_response`, `nms_radius`).

use super::planes::{blur, smoothed_gradients};
use super::{sized, KeypointParams, Scratch};

/// Integration scale of the Harris structure tensor, in working pixels.
const INTEGRATION_SIGMA: f32 = 2.0;

/// Harris detection on `s.level` (`w x h`): pushes `(response, x, y, octave)` of every local
/// maximum above the thresholds to `s.candidates`, and leaves the gradients in `s.gx`, `s.gy`.
pub(super) fn detect(s: &mut Scratch, w: usize, h: usize, octave: u8, params: &KeypointParams) {
    let n = w * h;
    smoothed_gradients(s, w, h);
    let Scratch {
        tmp,
        gx,
        gy,
        sxx,
        syy,
        sxy,
        response,
        dilated,
        padded,
        candidates,
        ..
    } = s;
    let (gx, gy) = (&gx[..n], &gy[..n]);
    // Products of gradients, then their Gaussian-weighted sums (the structure tensor).
    {
        let (pxx, pyy, pxy) = (sized(sxx, n), sized(syy, n), sized(sxy, n));
        for i in 0..n {
            let (a, b) = (gx[i], gy[i]);
            pxx[i] = a * a;
            pyy[i] = b * b;
            pxy[i] = a * b;
        }
    }
    let out = sized(response, n);
    for plane in [&mut *sxx, &mut *syy, &mut *sxy] {
        out.copy_from_slice(&plane[..n]);
        blur(out, &mut plane[..n], tmp, padded, w, h, INTEGRATION_SIGMA);
    }
    let k = params.harris_k;
    let mut max = 0.0f32;
    for i in 0..n {
        let (a, b, c) = (sxx[i], syy[i], sxy[i]);
        let r = a * b - c * c - k * (a + b) * (a + b);
        out[i] = r;
        max = max.max(r);
    }
    let threshold = (max * params.relative_threshold).max(params.min_response);
    // Window maximum (separable dilation), then keep the pixels equal to it.
    let rad = params.nms_radius as usize;
    let dil = sized(dilated, n);
    let tmp = sized(tmp, n);
    for y in 0..h {
        let row = &out[y * w..(y + 1) * w];
        for x in 0..w {
            let (a, b) = (x.saturating_sub(rad), (x + rad).min(w - 1));
            tmp[y * w + x] = row[a..=b].iter().copied().fold(f32::MIN, f32::max);
        }
    }
    for y in 0..h {
        let (a, b) = (y.saturating_sub(rad), (y + rad).min(h - 1));
        let d = &mut dil[y * w..(y + 1) * w];
        d.copy_from_slice(&tmp[a * w..(a + 1) * w]);
        for yy in a + 1..=b {
            for (o, &v) in d.iter_mut().zip(&tmp[yy * w..(yy + 1) * w]) {
                *o = o.max(v);
            }
        }
    }
    let first = candidates.len();
    for y in 0..h {
        for x in 0..w {
            let v = out[y * w + x];
            if v > threshold && v >= dil[y * w + x] {
                candidates.push((v, x as u32, y as u32, octave));
            }
        }
    }
    // Plateaus: of equal maxima within the radius keep the first in raster order.
    let mut kept = first;
    for i in first..candidates.len() {
        let c = candidates[i];
        let dup = candidates[first..kept]
            .iter()
            .rev()
            .take_while(|o| o.2 as usize + rad >= c.2 as usize)
            .any(|o| {
                o.0 == c.0
                    && (o.1 as usize).abs_diff(c.1 as usize) <= rad
                    && (o.2 as usize).abs_diff(c.2 as usize) <= rad
            });
        if !dup {
            candidates[kept] = c;
            kept += 1;
        }
    }
    candidates.truncate(kept);
}
