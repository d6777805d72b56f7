//! Image -> network input: resize (stretch, or short side + centre crop), per-channel
//! `(x - mean) / scale` on 0..255 RGB values, planar NCHW layout.
//!
//! This is the part of "preprocess as the model needs" that does not depend on the network, so
//! it is a plain function of [`CnnOptions`] and is tested without a model.
//!
//! Invariants: the output always holds exactly `3 * width * height` finite values (the
//! `input_size` of the options), channel planes in R, G, B order; any non-empty image of any
//! size and colour type is accepted (grey is replicated to three channels, alpha is dropped).
//! Resizing uses a triangle (bilinear) filter whose support widens when shrinking, i.e. the
//! antialiased bilinear resize of torchvision that ImageNet models are usually exported with;
//! colour conversion and resizing are the shared preparation path of `features` (`to_rgb`,
//! `resize_rgb`).

use image::imageops;
use image::{DynamicImage, RgbImage};

use super::{CnnOptions, CnnResize};
use crate::features::{resize_rgb, to_rgb};
use crate::{Error, Result};

/// The network input of one image: `3 * h * w` values, planar R, G, B (one batch item of NCHW).
pub(crate) fn preprocess(options: &CnnOptions, image: &DynamicImage) -> Result<Vec<f32>> {
    let (width, height) = (image.width(), image.height());
    if width == 0 || height == 0 {
        return Err(Error::Image {
            name: "cnn input".into(),
            reason: format!("a {width}x{height} image has no pixels"),
        });
    }
    let rgb = to_rgb(image);
    let (out_w, out_h) = options.input_size;
    match options.resize {
        CnnResize::Stretch => {
            let sized = resize_rgb(&rgb, out_w, out_h)?;
            Ok(to_planar(&sized, options.mean, options.scale))
        }
        CnnResize::ShortSideCrop { short_side } => {
            let (rw, rh) = short_side_size(width, height, short_side);
            let resized = resize_rgb(&rgb, rw, rh)?;
            let (x0, y0) = (centre_offset(rw, out_w), centre_offset(rh, out_h));
            let crop = imageops::crop_imm(resized.as_ref(), x0, y0, out_w, out_h).to_image();
            Ok(to_planar(&crop, options.mean, options.scale))
        }
    }
}

/// Size after scaling the short side to `short_side`, keeping the aspect ratio; the long side
/// is truncated like torchvision's `Resize(int)`. Never smaller than `short_side` on either side.
pub(crate) fn short_side_size(width: u32, height: u32, short_side: u32) -> (u32, u32) {
    let scaled = |long: u32, short: u32| {
        let v = u64::from(short_side) * u64::from(long) / u64::from(short);
        u32::try_from(v).unwrap_or(u32::MAX).max(short_side)
    };
    if width <= height {
        (short_side, scaled(height, width))
    } else {
        (scaled(width, height), short_side)
    }
}

/// Left/top offset of a centred window of `inner` pixels in `outer` pixels (`inner <= outer`),
/// rounded like torchvision's `CenterCrop`.
fn centre_offset(outer: u32, inner: u32) -> u32 {
    outer.saturating_sub(inner).div_ceil(2)
}

/// The README preprocessing's planar layout of an already sized image, for tests comparing
/// resize paths.
#[cfg(test)]
pub(crate) fn to_planar_for_tests(rgb: &RgbImage) -> Vec<f32> {
    to_planar(rgb, [127.0; 3], [128.0; 3])
}

fn to_planar(rgb: &RgbImage, mean: [f32; 3], scale: [f32; 3]) -> Vec<f32> {
    let plane = rgb.as_raw().len() / 3;
    let mut out = vec![0.0f32; 3 * plane];
    let (r, rest) = out.split_at_mut(plane);
    let (g, b) = rest.split_at_mut(plane);
    let inv = scale.map(|s| 1.0 / s);
    for (((px, r), g), b) in rgb
        .as_raw()
        .chunks_exact(3)
        .zip(r.iter_mut())
        .zip(g.iter_mut())
        .zip(b.iter_mut())
    {
        *r = (f32::from(px[0]) - mean[0]) * inv[0];
        *g = (f32::from(px[1]) - mean[1]) * inv[1];
        *b = (f32::from(px[2]) - mean[2]) * inv[2];
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{GrayImage, Luma, Rgb};
    use proptest::prelude::*;
    use std::path::PathBuf;

    fn options(input_size: (u32, u32), resize: CnnResize) -> CnnOptions {
        CnnOptions {
            model: PathBuf::from("unused.onnx"),
            layer: "unused".into(),
            input_size,
            resize,
            mean: [127.0, 127.0, 127.0],
            scale: [128.0, 128.0, 128.0],
        }
    }

    fn plane(values: &[f32], c: usize, size: (u32, u32)) -> &[f32] {
        let n = (size.0 * size.1) as usize;
        &values[c * n..(c + 1) * n]
    }

    #[test]
    fn uniform_image_becomes_normalised_planes_in_rgb_order() {
        let img = DynamicImage::ImageRgb8(RgbImage::from_pixel(10, 6, Rgb([255, 127, 63])));
        let mut opts = options((4, 4), CnnResize::Stretch);
        opts.scale = [128.0, 64.0, 32.0];
        let x = preprocess(&opts, &img).unwrap();
        assert_eq!(x.len(), 3 * 16);
        let expected = [128.0 / 128.0, 0.0, -64.0 / 32.0];
        for (c, want) in expected.iter().enumerate() {
            for v in plane(&x, c, (4, 4)) {
                assert!((v - want).abs() < 1e-6, "channel {c}: {v} != {want}");
            }
        }
    }

    /// A 64x32 frame with red, green and blue vertical bands: the README centre crop keeps the
    /// middle 44 % of the width (only green), stretching keeps all three bands.
    #[test]
    fn short_side_crop_keeps_the_centre_and_stretch_keeps_everything() {
        let img = RgbImage::from_fn(64, 32, |x, _| match x {
            0..16 => Rgb([255, 0, 0]),
            16..48 => Rgb([0, 255, 0]),
            _ => Rgb([0, 0, 255]),
        });
        let img = DynamicImage::ImageRgb8(img);
        let size = (224, 224);
        let crop = preprocess(
            &options(size, CnnResize::ShortSideCrop { short_side: 256 }),
            &img,
        )
        .unwrap();
        let red = plane(&crop, 0, size);
        assert!(
            red.iter().all(|&v| v < -0.99),
            "the crop must not reach the red band"
        );
        let stretch = preprocess(&options(size, CnnResize::Stretch), &img).unwrap();
        let red = plane(&stretch, 0, size);
        assert!(red[0] > 0.99, "stretch keeps the red band at the left edge");
        assert!(red[223] < -0.99, "and no red at the right edge");
        assert!(plane(&stretch, 2, size)[223] > 0.99);
    }

    #[test]
    fn short_side_size_keeps_aspect_and_truncates_like_torchvision() {
        assert_eq!(short_side_size(64, 32, 256), (512, 256));
        assert_eq!(short_side_size(773, 512, 256), (386, 256));
        assert_eq!(short_side_size(500, 500, 256), (256, 256));
        assert_eq!(short_side_size(1, 1000, 4), (4, 4000));
        assert_eq!(centre_offset(512, 224), 144);
        assert_eq!(centre_offset(225, 224), 1);
    }

    #[test]
    fn grey_images_are_replicated_to_three_channels() {
        let img = DynamicImage::ImageLuma8(GrayImage::from_pixel(8, 8, Luma([200])));
        let size = (8, 8);
        let x = preprocess(&options(size, CnnResize::Stretch), &img).unwrap();
        let want = (200.0 - 127.0) / 128.0;
        assert!(x.iter().all(|v| (v - want).abs() < 1e-6));
    }

    #[test]
    fn empty_images_are_rejected() {
        let img = DynamicImage::ImageRgb8(RgbImage::new(0, 5));
        let err = preprocess(&options((4, 4), CnnResize::Stretch), &img).unwrap_err();
        assert!(err.to_string().contains("0x5"), "{err}");
    }

    proptest! {
        #[test]
        fn output_has_the_input_size_and_is_finite(
            w in 1u32..80, h in 1u32..80, crop in any::<bool>(), seed in any::<u8>(),
        ) {
            let img = RgbImage::from_fn(w, h, |x, y| {
                let v = (x * 7 + y * 13 + u32::from(seed)) as u8;
                Rgb([v, v.wrapping_mul(3), 255 - v])
            });
            let resize = if crop {
                CnnResize::ShortSideCrop { short_side: 40 }
            } else {
                CnnResize::Stretch
            };
            let x = preprocess(&options((32, 24), resize), &DynamicImage::ImageRgb8(img)).unwrap();
            prop_assert_eq!(x.len(), 3 * 32 * 24);
            prop_assert!(x.iter().all(|v| v.is_finite() && v.abs() <= 1.0));
        }
    }
}
