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
//!
//! Code: this file holds the parameters, the output types and the pipeline of one image
//! ([`extract`]: working image, octaves, strongest-first selection); `keypoints/planes.rs` the
//! image operations (resampling, halving, Gaussian blur, gradients), `keypoints/harris.rs` the
//! detector and `keypoints/descriptor.rs` the descriptor.

use std::cell::RefCell;

use image::GrayImage;

use crate::{Error, Result};

mod descriptor;
mod harris;
mod planes;

use descriptor::{describe, orientation_planes, weight_table};
use harris::detect;
use planes::{halve, resample};

/// Length of one descriptor.
pub const DESCRIPTOR_DIM: usize = 128;

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

    /// A deterministic textured image: overlapping rectangles of several sizes and grey
    /// levels over a gentle gradient, from a fixed linear congruential sequence.
    fn texture(w: u32, h: u32) -> GrayImage {
        let mut state = 0x2545_f491u32;
        let mut next = |m: u32| {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) % m
        };
        let mut img = GrayImage::from_fn(w, h, |x, y| Luma([(30 + (x + 2 * y) % 40) as u8]));
        for _ in 0..40 {
            let (x0, y0, rw, rh, v) = (next(w), next(h), 4 + next(24), 4 + next(24), next(256));
            for y in y0..(y0 + rh).min(h) {
                for x in x0..(x0 + rw).min(w) {
                    img.put_pixel(x, y, Luma([v as u8]));
                }
            }
        }
        img
    }

    /// Pins every bit of the output (positions, responses, octaves, descriptors) on a fixed
    /// image, so a refactoring of the detector or the descriptor that changes a value fails
    /// here, not only in recognition quality. A deliberate change of the features updates the
    /// digest (and is measured on real images, `docs/cooc.md`).
    #[test]
    fn the_output_on_a_fixed_image_is_pinned() {
        use sha2::{Digest, Sha256};
        let f = extract("texture", &texture(320, 240), &KeypointParams::default()).unwrap();
        assert!(f.keypoints.len() > 50, "{} keypoints", f.keypoints.len());
        let mut h = Sha256::new();
        for k in &f.keypoints {
            h.update(k.x.to_bits().to_le_bytes());
            h.update(k.y.to_bits().to_le_bytes());
            h.update(k.response.to_bits().to_le_bytes());
            h.update([k.octave]);
        }
        for v in &f.descriptors {
            h.update(v.to_bits().to_le_bytes());
        }
        let digest: String = h.finalize().iter().map(|b| format!("{b:02x}")).collect();
        assert_eq!(
            (f.keypoints.len(), digest.as_str()),
            (
                195,
                "b6528ec84802f5100f71b755579d25a37cb2dee0de601f758eb367affba3739d"
            ),
            "keypoints or descriptors changed on the fixed image"
        );
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
