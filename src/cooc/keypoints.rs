//! Local features: Harris corners on a working-resolution grayscale image (optionally over a
//! pyramid of octaves), each described by an upright SIFT-like 128-D gradient histogram
//! (4 x 4 cells x 8 orientations).
//!
//! Why this choice: the paper uses SIFT; a float descriptor clusters naturally with Euclidean
//! k-means (binary descriptors need k-majority or k-medoids and quantise worse at small
//! vocabularies). Rotation invariance is dropped on purpose: a vehicle camera stays upright, and
//! upright descriptors are more discriminative and cheaper.
//!
//! **Working resolution.** Every image is first resampled to a working size: upsampled by
//! [`KeypointParams::upsample`] (bilinear), but never wider than [`KeypointParams::max_width`]
//! (larger images are reduced by area averaging, aspect kept). Nordland's 64x32 frames are
//! upsampled 2x, so corners have room and the descriptor a patch of a few original pixels; a
//! 960x540 and a 640x360 camera of the same scene both work at 640 px wide, so their features
//! have the same scale and every later stage costs the same whatever the camera. All sizes
//! below (smoothing, NMS radius, descriptor cells) are in working pixels.
//!
//! **Octaves.** With `octaves > 1` corners are also detected on the working image halved once
//! or more (2x2 averaging) and described there with the same cell size, i.e. with a patch twice
//! as large: a coarse scale selection for scenes seen from another distance.
//!
//! Speed: every plane of one image lives in one per-thread scratch buffer that is reused from
//! image to image, and descriptors are written straight into the output (no allocation per
//! keypoint).
//!
//! Invariants: keypoint positions are normalised to `[0, 1)` in both axes (independent of the
//! image size); descriptors have [`DESCRIPTOR_DIM`] finite values and unit L2 norm (or are all
//! zero for a perfectly flat patch); the output is deterministic.

use std::cell::RefCell;

use image::GrayImage;

use crate::{Error, Result};

/// Length of one descriptor.
pub const DESCRIPTOR_DIM: usize = 128;

/// Pre-smoothing of the working image before gradients, in working pixels.
const SMOOTH_SIGMA: f32 = 1.0;
/// Integration scale of the Harris structure tensor, in working pixels.
const INTEGRATION_SIGMA: f32 = 2.0;

/// Detector and descriptor settings.
#[derive(Clone, Debug, PartialEq)]
pub struct KeypointParams {
    /// Bilinear upsampling factor applied before detection (1 = none), capped by `max_width`.
    pub upsample: u32,
    /// Largest working width in pixels (wider images are reduced, aspect kept); 0 = no cap.
    pub max_width: u32,
    /// Keep at most this many keypoints per image (strongest Harris response first).
    pub max_keypoints: usize,
    /// Harris `k` in `det - k * trace^2`.
    pub harris_k: f32,
    /// Keep responses above this fraction of the image's strongest response.
    pub relative_threshold: f32,
    /// Keep responses above this absolute value (intensities in `[0, 1]`, gradients per
    /// working pixel); rejects noise in near-black frames, where the relative threshold alone
    /// would keep sensor noise.
    pub min_response: f32,
    /// Non-maximum suppression radius, in working pixels.
    pub nms_radius: u32,
    /// Side of one of the 4 x 4 descriptor cells, in working pixels.
    pub cell_size: u32,
    /// Detection octaves (1 = the working image only; each further one halves it).
    pub octaves: u32,
}

impl Default for KeypointParams {
    fn default() -> Self {
        KeypointParams {
            upsample: 2,
            max_width: 640,
            max_keypoints: 300,
            harris_k: 0.04,
            relative_threshold: 1e-5,
            min_response: 0.0,
            nms_radius: 2,
            cell_size: 3,
            octaves: 1,
        }
    }
}

impl KeypointParams {
    /// Fails with [`Error::InvalidParameter`] naming the first out-of-range parameter.
    pub fn validate(&self) -> Result<()> {
        if !(1..=8).contains(&self.upsample) {
            return Err(Error::param(
                "upsample",
                format!("must be in 1..=8, got {}", self.upsample),
            ));
        }
        if self.max_width != 0 && !(16..=8192).contains(&self.max_width) {
            return Err(Error::param(
                "max_width",
                format!("must be 0 (no cap) or in 16..=8192, got {}", self.max_width),
            ));
        }
        if !(1..=2000).contains(&self.max_keypoints) {
            return Err(Error::param(
                "max_keypoints",
                format!("must be in 1..=2000, got {}", self.max_keypoints),
            ));
        }
        if !(self.harris_k > 0.0 && self.harris_k < 0.25) {
            return Err(Error::param(
                "harris_k",
                format!("must be in (0, 0.25), got {}", self.harris_k),
            ));
        }
        if !(0.0..1.0).contains(&self.relative_threshold) {
            return Err(Error::param(
                "relative_threshold",
                format!("must be in [0, 1), got {}", self.relative_threshold),
            ));
        }
        if !(self.min_response >= 0.0 && self.min_response.is_finite()) {
            return Err(Error::param(
                "min_response",
                format!("must be finite and >= 0, got {}", self.min_response),
            ));
        }
        if !(1..=64).contains(&self.nms_radius) {
            return Err(Error::param(
                "nms_radius",
                format!("must be in 1..=64, got {}", self.nms_radius),
            ));
        }
        if !(1..=64).contains(&self.cell_size) {
            return Err(Error::param(
                "cell_size",
                format!("must be in 1..=64, got {}", self.cell_size),
            ));
        }
        if !(1..=4).contains(&self.octaves) {
            return Err(Error::param(
                "octaves",
                format!("must be in 1..=4, got {}", self.octaves),
            ));
        }
        Ok(())
    }

    /// The working size of a `w x h` image (see the module documentation).
    pub fn working_size(&self, w: u32, h: u32) -> (usize, usize) {
        let (w, h) = (w as usize, h as usize);
        let up = self.upsample as usize;
        let cap = self.max_width as usize;
        if cap == 0 || w * up <= cap {
            (w * up, h * up)
        } else {
            let h2 = ((h as f64 * cap as f64 / w as f64).round() as usize).max(1);
            (cap, h2)
        }
    }
}

/// One detected keypoint.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Keypoint {
    /// Horizontal position, normalised to `[0, 1)` (0 = left edge).
    pub x: f32,
    /// Vertical position, normalised to `[0, 1)` (0 = top edge).
    pub y: f32,
    /// Harris response (higher = stronger corner).
    pub response: f32,
    /// Octave it was detected in (0 = the working image).
    pub octave: u8,
}

/// The keypoints of one image and their descriptors (row `k` belongs to keypoint `k`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Features {
    /// Keypoints, strongest first.
    pub keypoints: Vec<Keypoint>,
    /// `keypoints.len() * DESCRIPTOR_DIM` values, row-major.
    pub descriptors: Vec<f32>,
}

impl Features {
    /// Descriptor of keypoint `k`.
    pub fn descriptor(&self, k: usize) -> &[f32] {
        &self.descriptors[k * DESCRIPTOR_DIM..(k + 1) * DESCRIPTOR_DIM]
    }
}

/// Reusable per-thread buffers: every plane of one octave. Grown on demand, never shrunk.
#[derive(Default)]
struct Scratch {
    level: Vec<f32>,
    next: Vec<f32>,
    tmp: Vec<f32>,
    smooth: Vec<f32>,
    gx: Vec<f32>,
    gy: Vec<f32>,
    sxx: Vec<f32>,
    syy: Vec<f32>,
    sxy: Vec<f32>,
    response: Vec<f32>,
    dilated: Vec<f32>,
    magnitude: Vec<f32>,
    orientation: Vec<f32>,
    padded: Vec<f32>,
    weights: Vec<f32>,
    candidates: Vec<(f32, u32, u32, u8)>,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

fn sized(v: &mut Vec<f32>, n: usize) -> &mut [f32] {
    if v.len() < n {
        v.resize(n, 0.0);
    }
    &mut v[..n]
}

/// Detects and describes the keypoints of `image` (`name` appears in errors).
pub fn extract(name: &str, image: &GrayImage, params: &KeypointParams) -> Result<Features> {
    params.validate()?;
    let (w0, h0) = image.dimensions();
    if w0 < 4 || h0 < 4 {
        return Err(Error::Image {
            name: name.to_string(),
            reason: format!("{w0}x{h0} is too small for keypoints (at least 4x4)"),
        });
    }
    SCRATCH.with(|s| {
        let mut s = s.borrow_mut();
        Ok(extract_with(&mut s, image, params))
    })
}

fn extract_with(s: &mut Scratch, image: &GrayImage, params: &KeypointParams) -> Features {
    let (mut w, mut h) = params.working_size(image.width(), image.height());
    resample(image, w, h, s);
    s.candidates.clear();
    // Detection on every octave: candidates (response, x, y, octave) in level pixels.
    let mut dims = Vec::with_capacity(params.octaves as usize);
    for octave in 0..params.octaves as u8 {
        if w < 8 || h < 8 {
            break;
        }
        if octave > 0 {
            halve(s, w, h);
            (w, h) = (w / 2, h / 2);
        }
        dims.push((w, h));
        detect(s, w, h, octave, params);
    }
    // Strongest first over all octaves; ties in (octave, raster) order.
    let mut c = std::mem::take(&mut s.candidates);
    c.sort_by(|a, b| {
        b.0.total_cmp(&a.0)
            .then((a.3, a.2, a.1).cmp(&(b.3, b.2, b.1)))
    });
    c.truncate(params.max_keypoints);
    // Describe octave by octave (the level planes are rebuilt in order).
    c.sort_by_key(|k| (k.3, k.2, k.1));
    let mut descriptors = vec![0.0f32; c.len() * DESCRIPTOR_DIM];
    let mut keypoints = Vec::with_capacity(c.len());
    let (mut w, mut h) = params.working_size(image.width(), image.height());
    if !c.is_empty() {
        resample(image, w, h, s);
    }
    let mut k = 0;
    for (octave, &(lw, lh)) in dims.iter().enumerate() {
        let end = k + c[k..].iter().take_while(|x| x.3 as usize == octave).count();
        if octave > 0 && k < c.len() {
            halve(s, w, h);
        }
        (w, h) = (lw, lh);
        if k == end {
            continue;
        }
        orientation_planes(s, w, h);
        weight_table(&mut s.weights, params.cell_size as usize);
        for (i, cand) in c[k..end].iter().enumerate() {
            let out = &mut descriptors[(k + i) * DESCRIPTOR_DIM..(k + i + 1) * DESCRIPTOR_DIM];
            describe(
                s,
                w,
                h,
                cand.1 as usize,
                cand.2 as usize,
                params.cell_size as usize,
                out,
            );
            keypoints.push(Keypoint {
                x: (cand.1 as f32 + 0.5) / w as f32,
                y: (cand.2 as f32 + 0.5) / h as f32,
                response: cand.0,
                octave: cand.3,
            });
        }
        k = end;
    }
    // Back to strongest first.
    let mut order: Vec<usize> = (0..keypoints.len()).collect();
    order.sort_by(|&a, &b| {
        let (ka, kb) = (&keypoints[a], &keypoints[b]);
        kb.response
            .total_cmp(&ka.response)
            .then((c[a].3, c[a].2, c[a].1).cmp(&(c[b].3, c[b].2, c[b].1)))
    });
    let mut sorted_desc = Vec::with_capacity(descriptors.len());
    for &i in &order {
        sorted_desc.extend_from_slice(&descriptors[i * DESCRIPTOR_DIM..(i + 1) * DESCRIPTOR_DIM]);
    }
    let keypoints = order.iter().map(|&i| keypoints[i]).collect();
    s.candidates = c;
    Features {
        keypoints,
        descriptors: sorted_desc,
    }
}

/// Resamples `image` to `w x h` into `s.level`, intensities in `[0, 1]`: bilinear (pixel
/// centres aligned) when enlarging an axis, area averaging when reducing it. Separable.
fn resample(image: &GrayImage, w: usize, h: usize, s: &mut Scratch) {
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
fn halve(s: &mut Scratch, w: usize, h: usize) {
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
fn blur(
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

/// Harris detection on `s.level` (`w x h`): pushes `(response, x, y, octave)` of every local
/// maximum above the thresholds to `s.candidates`, and leaves the gradients in `s.gx`, `s.gy`.
fn detect(s: &mut Scratch, w: usize, h: usize, octave: u8, params: &KeypointParams) {
    let n = w * h;
    let Scratch {
        level,
        tmp,
        smooth,
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
    let smooth = sized(smooth, n);
    blur(&level[..n], smooth, tmp, padded, w, h, SMOOTH_SIGMA);
    let (gx, gy) = (sized(gx, n), sized(gy, n));
    gradients(smooth, gx, gy, w, h);
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

/// Gradient magnitude and orientation (in eighths of a turn, `[0, 8)`) of the current level's
/// smoothed image (recomputed from `s.level`).
fn orientation_planes(s: &mut Scratch, w: usize, h: usize) {
    let n = w * h;
    let Scratch {
        level,
        tmp,
        smooth,
        gx,
        gy,
        magnitude,
        orientation,
        padded,
        ..
    } = s;
    let smooth = sized(smooth, n);
    blur(&level[..n], smooth, tmp, padded, w, h, SMOOTH_SIGMA);
    let (gx, gy) = (sized(gx, n), sized(gy, n));
    gradients(smooth, gx, gy, w, h);
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
fn weight_table(out: &mut Vec<f32>, cell: usize) {
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
fn describe(s: &Scratch, w: usize, h: usize, cx: usize, cy: usize, cell: usize, out: &mut [f32]) {
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

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use image::Luma;

    /// A dark image with bright axis-aligned squares at the given top-left corners.
    pub(crate) fn squares(w: u32, h: u32, corners: &[(u32, u32)], side: u32) -> GrayImage {
        let mut img = GrayImage::from_pixel(w, h, Luma([20]));
        for &(x0, y0) in corners {
            for y in y0..(y0 + side).min(h) {
                for x in x0..(x0 + side).min(w) {
                    img.put_pixel(x, y, Luma([220]));
                }
            }
        }
        img
    }

    #[test]
    fn finds_the_corners_of_a_square() {
        let img = squares(64, 32, &[(20, 8)], 12);
        let f = extract("sq", &img, &KeypointParams::default()).unwrap();
        // The four corners, in normalised coordinates.
        let corners = [(20.0, 8.0), (32.0, 8.0), (20.0, 20.0), (32.0, 20.0)];
        for (cx, cy) in corners {
            let (nx, ny) = (cx / 64.0, cy / 32.0);
            let near = f
                .keypoints
                .iter()
                .any(|k| (k.x - nx).abs() < 1.5 / 64.0 && (k.y - ny).abs() < 1.5 / 32.0);
            assert!(
                near,
                "no keypoint near corner ({cx}, {cy}): {:?}",
                f.keypoints
            );
        }
        assert_eq!(f.descriptors.len(), f.keypoints.len() * DESCRIPTOR_DIM);
    }

    #[test]
    fn flat_image_has_no_keypoints() {
        let img = GrayImage::from_pixel(64, 32, Luma([90]));
        let f = extract("flat", &img, &KeypointParams::default()).unwrap();
        assert!(f.keypoints.is_empty());
    }

    #[test]
    fn descriptors_are_unit_and_distinguish_corner_types() {
        let img = squares(64, 32, &[(20, 8)], 12);
        let f = extract("sq", &img, &KeypointParams::default()).unwrap();
        for k in 0..f.keypoints.len() {
            let n: f32 = f.descriptor(k).iter().map(|x| x * x).sum();
            assert!((n - 1.0).abs() < 1e-3, "norm^2 {n}");
        }
        // Top-left and bottom-right corners look different (gradients point opposite ways).
        let find = |cx: f32, cy: f32| {
            f.keypoints
                .iter()
                .position(|k| {
                    (k.x - cx / 64.0).abs() < 1.5 / 64.0 && (k.y - cy / 32.0).abs() < 1.5 / 32.0
                })
                .expect("corner detected")
        };
        let (a, b) = (find(20.0, 8.0), find(32.0, 20.0));
        let dot: f32 = f
            .descriptor(a)
            .iter()
            .zip(f.descriptor(b))
            .map(|(x, y)| x * y)
            .sum();
        assert!(dot < 0.5, "opposite corners too similar: {dot}");
    }

    #[test]
    fn keypoints_follow_a_translation() {
        let p = KeypointParams::default();
        let a = extract("a", &squares(64, 32, &[(10, 6)], 10), &p).unwrap();
        let b = extract("b", &squares(64, 32, &[(30, 6)], 10), &p).unwrap();
        assert_eq!(a.keypoints.len(), b.keypoints.len());
        for (ka, kb) in a.keypoints.iter().zip(&b.keypoints) {
            assert!((kb.x - ka.x - 20.0 / 64.0).abs() < 1e-3);
            assert!((kb.y - ka.y).abs() < 1e-3);
        }
    }

    #[test]
    fn rejects_tiny_images_by_name() {
        let err = extract(
            "tiny.png",
            &GrayImage::new(3, 3),
            &KeypointParams::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("tiny.png"), "{err}");
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(16))]
        #[test]
        fn arbitrary_images_give_finite_bounded_output(
            w in 4u32..40, h in 4u32..24, seed in 0u64..1000,
        ) {
            let mut rng = crate::cooc::SplitMix64::new(seed);
            let img = GrayImage::from_fn(w, h, |_, _| Luma([(rng.next_u64() & 255) as u8]));
            let p = KeypointParams { upsample: 2, ..KeypointParams::default() };
            let f = extract("rand", &img, &p).unwrap();
            proptest::prop_assert!(f.keypoints.len() <= p.max_keypoints);
            proptest::prop_assert_eq!(f.descriptors.len(), f.keypoints.len() * DESCRIPTOR_DIM);
            proptest::prop_assert!(f.descriptors.iter().all(|v| v.is_finite()));
            proptest::prop_assert!(f.keypoints.iter().all(|k| (0.0..1.0).contains(&k.x) && (0.0..1.0).contains(&k.y)));
        }
    }
}
