//! Local features: Harris corners on an upsampled grayscale image, each described by an upright
//! SIFT-like 128-D gradient histogram (4 x 4 cells x 8 orientations).
//!
//! Why this choice: the paper uses SIFT; a float descriptor clusters naturally with Euclidean
//! k-means (binary descriptors need k-majority or k-medoids and quantise worse at small
//! vocabularies). Rotation invariance is dropped on purpose: a vehicle camera stays upright, and
//! upright descriptors are more discriminative and cheaper. Scale selection is dropped too: the
//! route is driven with the same camera, so features reappear at similar scale.
//!
//! Why upsample: Nordland frames are 64x32 pixels, so corners at native resolution are one or two
//! pixels apart and a 16x16 SIFT patch covers half the image. The image is bilinearly upsampled
//! by [`KeypointParams::upsample`] first; detection and description then work at a sub-pixel
//! scale of the original (documented in `docs/cooc.md` with measured repeatability).
//!
//! Invariants: keypoint positions are normalised to `[0, 1)` in both axes (independent of the
//! image size); descriptors have [`DESCRIPTOR_DIM`] finite values and unit L2 norm (or are all
//! zero for a perfectly flat patch); the output is deterministic.

use image::GrayImage;

use crate::{Error, Result};

/// Length of one descriptor.
pub const DESCRIPTOR_DIM: usize = 128;

/// Detector and descriptor settings.
#[derive(Clone, Debug, PartialEq)]
pub struct KeypointParams {
    /// Bilinear upsampling factor applied before detection (1 = none).
    pub upsample: u32,
    /// Keep at most this many keypoints per image (strongest Harris response first).
    pub max_keypoints: usize,
    /// Harris `k` in `det - k * trace^2`.
    pub harris_k: f32,
    /// Keep responses above this fraction of the image's strongest response.
    pub relative_threshold: f32,
    /// Keep responses above this absolute value (intensities in `[0, 1]`); rejects noise in
    /// near-black frames, where the relative threshold alone would keep sensor noise.
    pub min_response: f32,
    /// Non-maximum suppression radius, in upsampled pixels.
    pub nms_radius: u32,
    /// Side of one of the 4 x 4 descriptor cells, in upsampled pixels.
    pub cell_size: u32,
}

impl Default for KeypointParams {
    fn default() -> Self {
        KeypointParams {
            upsample: 2,
            max_keypoints: 80,
            harris_k: 0.04,
            relative_threshold: 1e-5,
            min_response: 0.0,
            nms_radius: 2,
            cell_size: 3,
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
        if !(1..=1000).contains(&self.max_keypoints) {
            return Err(Error::param(
                "max_keypoints",
                format!("must be in 1..=1000, got {}", self.max_keypoints),
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
        Ok(())
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

/// A float image, row-major.
struct Plane {
    w: usize,
    h: usize,
    v: Vec<f32>,
}

impl Plane {
    #[inline]
    fn at(&self, x: usize, y: usize) -> f32 {
        self.v[y * self.w + x]
    }
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
    let up = upsample(image, params.upsample);
    let smooth = blur(&up, 0.5 * params.upsample as f32);
    let (gx, gy) = gradients(&smooth, params.upsample as f32);
    let response = harris(&gx, &gy, params.upsample as f32, params.harris_k);
    let mut kps = select(&response, params);
    let (w, h) = (up.w as f32, up.h as f32);
    let mut descriptors = Vec::with_capacity(kps.len() * DESCRIPTOR_DIM);
    for kp in &kps {
        describe(
            &gx,
            &gy,
            kp.0,
            kp.1,
            params.cell_size as usize,
            &mut descriptors,
        );
    }
    let keypoints = kps
        .drain(..)
        .map(|(x, y, r)| Keypoint {
            x: (x as f32 + 0.5) / w,
            y: (y as f32 + 0.5) / h,
            response: r,
        })
        .collect();
    Ok(Features {
        keypoints,
        descriptors,
    })
}

/// Bilinear upsampling by an integer factor into `[0, 1]` intensities (pixel centres aligned).
fn upsample(image: &GrayImage, factor: u32) -> Plane {
    let (w0, h0) = (image.width() as usize, image.height() as usize);
    let f = factor as usize;
    let (w, h) = (w0 * f, h0 * f);
    let src: Vec<f32> = image
        .as_raw()
        .iter()
        .map(|&p| f32::from(p) / 255.0)
        .collect();
    let mut v = vec![0.0f32; w * h];
    for y in 0..h {
        let sy = ((y as f32 + 0.5) / f as f32 - 0.5).clamp(0.0, (h0 - 1) as f32);
        let y0 = sy.floor() as usize;
        let y1 = (y0 + 1).min(h0 - 1);
        let ty = sy - y0 as f32;
        for x in 0..w {
            let sx = ((x as f32 + 0.5) / f as f32 - 0.5).clamp(0.0, (w0 - 1) as f32);
            let x0 = sx.floor() as usize;
            let x1 = (x0 + 1).min(w0 - 1);
            let tx = sx - x0 as f32;
            let top = src[y0 * w0 + x0] * (1.0 - tx) + src[y0 * w0 + x1] * tx;
            let bot = src[y1 * w0 + x0] * (1.0 - tx) + src[y1 * w0 + x1] * tx;
            v[y * w + x] = top * (1.0 - ty) + bot * ty;
        }
    }
    Plane { w, h, v }
}

/// Separable Gaussian blur with clamped borders. Rows are padded once and columns are
/// accumulated whole rows at a time, so both passes are straight-line loops the compiler
/// vectorises.
fn blur(p: &Plane, sigma: f32) -> Plane {
    let r = (3.0 * sigma).ceil().max(1.0) as usize;
    let kernel: Vec<f32> = (0..=2 * r)
        .map(|i| {
            let d = i as f32 - r as f32;
            (-(d * d) / (2.0 * sigma * sigma)).exp()
        })
        .collect();
    let sum: f32 = kernel.iter().sum();
    let kernel: Vec<f32> = kernel.iter().map(|k| k / sum).collect();
    let (w, h) = (p.w, p.h);
    let mut tmp = vec![0.0f32; p.v.len()];
    let mut padded = vec![0.0f32; w + 2 * r];
    for y in 0..h {
        let row = &p.v[y * w..(y + 1) * w];
        padded[..r].fill(row[0]);
        padded[r..r + w].copy_from_slice(row);
        padded[r + w..].fill(row[w - 1]);
        for (x, o) in tmp[y * w..(y + 1) * w].iter_mut().enumerate() {
            *o = kernel
                .iter()
                .zip(&padded[x..x + 2 * r + 1])
                .map(|(k, v)| k * v)
                .sum();
        }
    }
    let mut out = vec![0.0f32; p.v.len()];
    for y in 0..h {
        let dst = &mut out[y * w..(y + 1) * w];
        for (k, &kv) in kernel.iter().enumerate() {
            let yy = (y + k).saturating_sub(r).min(h - 1);
            for (o, &v) in dst.iter_mut().zip(&tmp[yy * w..(yy + 1) * w]) {
                *o += kv * v;
            }
        }
    }
    Plane { w, h, v: out }
}

/// Central-difference gradients (one-sided at the borders), per *original* pixel (`scale` =
/// upsampling factor), so responses and thresholds do not depend on the upsampling.
fn gradients(p: &Plane, scale: f32) -> (Plane, Plane) {
    let (w, h) = (p.w, p.h);
    let mut gx = vec![0.0f32; w * h];
    let mut gy = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let (xl, xr) = (x.saturating_sub(1), (x + 1).min(w - 1));
            let (yu, yd) = (y.saturating_sub(1), (y + 1).min(h - 1));
            gx[y * w + x] = scale * (p.at(xr, y) - p.at(xl, y)) / (xr - xl).max(1) as f32;
            gy[y * w + x] = scale * (p.at(x, yd) - p.at(x, yu)) / (yd - yu).max(1) as f32;
        }
    }
    (Plane { w, h, v: gx }, Plane { w, h, v: gy })
}

/// Harris response `det(M) - k trace(M)^2` of the Gaussian-weighted structure tensor `M`.
fn harris(gx: &Plane, gy: &Plane, sigma: f32, k: f32) -> Plane {
    let (w, h) = (gx.w, gx.h);
    let prod = |f: &dyn Fn(f32, f32) -> f32| Plane {
        w,
        h,
        v: gx.v.iter().zip(&gy.v).map(|(&a, &b)| f(a, b)).collect(),
    };
    let sxx = blur(&prod(&|a, _| a * a), sigma);
    let syy = blur(&prod(&|_, b| b * b), sigma);
    let sxy = blur(&prod(&|a, b| a * b), sigma);
    let v = (0..w * h)
        .map(|i| {
            let (a, b, c) = (sxx.v[i], syy.v[i], sxy.v[i]);
            a * b - c * c - k * (a + b) * (a + b)
        })
        .collect();
    Plane { w, h, v }
}

/// Local maxima above both thresholds, strongest first, at most `max_keypoints`.
fn select(r: &Plane, params: &KeypointParams) -> Vec<(usize, usize, f32)> {
    let max = r.v.iter().copied().fold(0.0f32, f32::max);
    let threshold = (max * params.relative_threshold).max(params.min_response);
    let rad = params.nms_radius as isize;
    let (w, h) = (r.w as isize, r.h as isize);
    let mut found = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let v = r.v[(y * w + x) as usize];
            if v <= threshold {
                continue;
            }
            // Strict maximum over earlier neighbours, >= over later ones: plateaus keep exactly
            // one point (the first in raster order).
            let mut is_max = true;
            'nb: for yy in (y - rad).max(0)..=(y + rad).min(h - 1) {
                for xx in (x - rad).max(0)..=(x + rad).min(w - 1) {
                    let o = r.v[(yy * w + xx) as usize];
                    let earlier = (yy, xx) < (y, x);
                    if o > v || (earlier && o == v) {
                        is_max = false;
                        break 'nb;
                    }
                }
            }
            if is_max {
                found.push((x as usize, y as usize, v));
            }
        }
    }
    found.sort_by(|a, b| b.2.total_cmp(&a.2).then((a.1, a.0).cmp(&(b.1, b.0))));
    found.truncate(params.max_keypoints);
    found
}

/// Appends the upright 4x4x8 gradient-histogram descriptor centred on `(cx, cy)`: bilinear in
/// space, linear in orientation, Gaussian-weighted, normalised, clipped at 0.2, renormalised.
fn describe(gx: &Plane, gy: &Plane, cx: usize, cy: usize, cell: usize, out: &mut Vec<f32>) {
    let mut hist = [0.0f32; DESCRIPTOR_DIM];
    let half = 2.0 * cell as f32; // the patch is 4 cells wide
    let sigma = half;
    let (w, h) = (gx.w as isize, gx.h as isize);
    let r = half.ceil() as isize;
    for dy in -r..r {
        for dx in -r..r {
            let (x, y) = (cx as isize + dx, cy as isize + dy);
            if x < 0 || y < 0 || x >= w || y >= h {
                continue;
            }
            let i = (y * w + x) as usize;
            let (a, b) = (gx.v[i], gy.v[i]);
            let mag = (a * a + b * b).sqrt();
            if mag == 0.0 {
                continue;
            }
            let (fx, fy) = (dx as f32 + 0.5, dy as f32 + 0.5);
            let weight = mag * (-(fx * fx + fy * fy) / (2.0 * sigma * sigma)).exp();
            // Cell coordinates with cell centres at integers 0..4.
            let u = (fx + half) / cell as f32 - 0.5;
            let v = (fy + half) / cell as f32 - 0.5;
            let angle = b.atan2(a).rem_euclid(std::f32::consts::TAU);
            let o = angle / std::f32::consts::TAU * 8.0;
            let (u0, v0, o0) = (u.floor(), v.floor(), o.floor());
            let (tu, tv, to) = (u - u0, v - v0, o - o0);
            for (cu, wu) in [(u0 as isize, 1.0 - tu), (u0 as isize + 1, tu)] {
                if !(0..4).contains(&cu) {
                    continue;
                }
                for (cv, wv) in [(v0 as isize, 1.0 - tv), (v0 as isize + 1, tv)] {
                    if !(0..4).contains(&cv) {
                        continue;
                    }
                    for (co, wo) in [(o0 as usize % 8, 1.0 - to), ((o0 as usize + 1) % 8, to)] {
                        hist[(cv as usize * 4 + cu as usize) * 8 + co] += weight * wu * wv * wo;
                    }
                }
            }
        }
    }
    normalize(&mut hist);
    for v in hist.iter_mut() {
        *v = v.min(0.2);
    }
    normalize(&mut hist);
    out.extend_from_slice(&hist);
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
