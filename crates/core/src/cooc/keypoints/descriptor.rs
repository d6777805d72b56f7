//! The upright SIFT-like descriptor: per level, the gradient magnitude and orientation
//! planes (a fast `atan2`), the Gaussian window of a patch, and the 4 x 4 cells x 8
//! orientations histogram of one keypoint (bilinear in space, linear in orientation,
//! normalised, clipped at 0.2, renormalised).
//!
//! Why apart: the descriptor is what the vocabulary tree quantises, with its own invariants
//! ([`super::DESCRIPTOR_DIM`] finite values, unit L2 norm or all zero); the detector only
//! chooses where it is computed.

use super::planes::smoothed_gradients;
use super::{sized, Scratch};

/// Gradient magnitude and orientation (in eighths of a turn, `[0, 8)`) of the current level's
/// smoothed image (recomputed from `s.level`).
pub(super) fn orientation_planes(s: &mut Scratch, w: usize, h: usize) {
    let n = w * h;
    smoothed_gradients(s, w, h);
    let Scratch {
        gx,
        gy,
        magnitude,
        orientation,
        ..
    } = s;
    let (gx, gy) = (&gx[..n], &gy[..n]);
    let (mag, ori) = (sized(magnitude, n), sized(orientation, n));
    for i in 0..n {
        let (a, b) = (gx[i], gy[i]);
        mag[i] = (a * a + b * b).sqrt();
        ori[i] = fast_atan2(b, a).rem_euclid(std::f32::consts::TAU) * (8.0 / std::f32::consts::TAU);
    }
}

/// `atan2(y, x)` within about 0.0015 rad (ample for 45-degree orientation bins).
#[inline]
fn fast_atan2(y: f32, x: f32) -> f32 {
    use std::f32::consts::{FRAC_PI_2, PI};
    let (ax, ay) = (x.abs(), y.abs());
    if ax == 0.0 && ay == 0.0 {
        return 0.0;
    }
    let (a, swap) = if ax >= ay {
        (ay / ax, false)
    } else {
        (ax / ay, true)
    };
    let s = a * a;
    let mut r = ((-0.046_496_474 * s + 0.159_314_22) * s - 0.327_622_77) * s * a + a;
    if swap {
        r = FRAC_PI_2 - r;
    }
    if x < 0.0 {
        r = PI - r;
    }
    if y < 0.0 {
        -r
    } else {
        r
    }
}

/// The Gaussian window of a descriptor patch of 4 cells of `cell` pixels, `(2r)^2` values.
pub(super) fn weight_table(out: &mut Vec<f32>, cell: usize) {
    let half = 2.0 * cell as f32;
    let r = half.ceil() as isize;
    let sigma = half;
    out.clear();
    for dy in -r..r {
        for dx in -r..r {
            let (fx, fy) = (dx as f32 + 0.5, dy as f32 + 0.5);
            out.push((-(fx * fx + fy * fy) / (2.0 * sigma * sigma)).exp());
        }
    }
}

/// Writes the upright 4x4x8 gradient-histogram descriptor centred on `(cx, cy)` into `out`:
/// bilinear in space, linear in orientation, Gaussian-weighted, normalised, clipped at 0.2,
/// renormalised.
pub(super) fn describe(
    s: &Scratch,
    w: usize,
    h: usize,
    cx: usize,
    cy: usize,
    cell: usize,
    out: &mut [f32],
) {
    let hist = out;
    hist.fill(0.0);
    let half = 2.0 * cell as f32; // the patch is 4 cells wide
    let r = half.ceil() as isize;
    let side = 2 * r as usize;
    let (w, h) = (w as isize, h as isize);
    let inv_cell = 1.0 / cell as f32;
    for dy in -r..r {
        let y = cy as isize + dy;
        if y < 0 || y >= h {
            continue;
        }
        let v = (dy as f32 + 0.5 + half) * inv_cell - 0.5;
        let v0 = v.floor();
        let tv = v - v0;
        let v0 = v0 as isize;
        for dx in -r..r {
            let x = cx as isize + dx;
            if x < 0 || x >= w {
                continue;
            }
            let i = (y * w + x) as usize;
            let mag = s.magnitude[i];
            if mag == 0.0 {
                continue;
            }
            let weight = mag * s.weights[(dy + r) as usize * side + (dx + r) as usize];
            // Cell coordinates with cell centres at integers 0..4.
            let u = (dx as f32 + 0.5 + half) * inv_cell - 0.5;
            let o = s.orientation[i];
            let (u0, o0) = (u.floor(), o.floor());
            let (tu, to) = (u - u0, o - o0);
            let (u0, o0) = (u0 as isize, o0 as usize % 8);
            let o1 = (o0 + 1) % 8;
            for (cv, wv) in [(v0, 1.0 - tv), (v0 + 1, tv)] {
                if !(0..4).contains(&cv) {
                    continue;
                }
                for (cu, wu) in [(u0, 1.0 - tu), (u0 + 1, tu)] {
                    if !(0..4).contains(&cu) {
                        continue;
                    }
                    let base = (cv as usize * 4 + cu as usize) * 8;
                    let wt = weight * wu * wv;
                    hist[base + o0] += wt * (1.0 - to);
                    hist[base + o1] += wt * to;
                }
            }
        }
    }
    normalize(hist);
    for v in hist.iter_mut() {
        *v = v.min(0.2);
    }
    normalize(hist);
}

fn normalize(v: &mut [f32]) {
    let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    if n > 1e-12 {
        v.iter_mut().for_each(|x| *x /= n);
    }
}
