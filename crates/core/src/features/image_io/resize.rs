//! Resizing with `fast_image_resize`'s bilinear (triangle, antialiased when shrinking)
//! convolution, one resizer per thread: [`resize_gray`] in 16-bit fixed point (enlarging by
//! the dedicated 2-tap kernel of `features::bilinear`), [`resize_rgb`] in `f32` rounded once
//! like `image`, and [`prepare_gray`], the preparation of every gray descriptor. The tolerance
//! against `image`'s resize is in the parent module's doc and pinned by the tests here.

use std::borrow::Cow;
use std::cell::RefCell;

use fast_image_resize as fir;
use image::{DynamicImage, GrayImage, RgbImage};

use super::colour::round_half_away_to_u8;
use super::to_gray;
use crate::{Error, Result};

/// Resizes a gray image to `width x height` with the triangle (bilinear, antialiased when
/// shrinking) filter; see the module doc for the tolerance against `image`'s resize. An image
/// of the requested size is returned as is (borrowed).
pub fn resize_gray(image: &GrayImage, width: u32, height: u32) -> Result<Cow<'_, GrayImage>> {
    if image.dimensions() == (width, height) {
        return Ok(Cow::Borrowed(image));
    }
    let (w, h) = image.dimensions();
    // Enlarging (two taps per axis): the dedicated kernel, bit for bit the same output.
    let out = match crate::features::bilinear::resize_gray_2tap(
        image.as_raw(),
        (w, h),
        (width, height),
    ) {
        Some(out) => out,
        None => resize_u8(image.as_raw(), (w, h), (width, height), fir::PixelType::U8)?,
    };
    GrayImage::from_raw(width, height, out)
        .map(Cow::Owned)
        .ok_or_else(|| buffer_error(width, height))
}

/// Resizes an 8-bit RGB image (the CNN input) with the same triangle filter, in `f32`: the
/// channels are filtered unrounded and rounded to 8 bits once at the end, as `image`'s resize
/// does, so the network sees (nearly always) the same pixels as before; CNN descriptors are
/// sensitive to one-level input changes, HOG is not. An image of the requested size is
/// returned as is (borrowed).
pub fn resize_rgb(image: &RgbImage, width: u32, height: u32) -> Result<Cow<'_, RgbImage>> {
    if image.dimensions() == (width, height) {
        return Ok(Cow::Borrowed(image));
    }
    let (w, h) = image.dimensions();
    check_sizes((w, h), (width, height))?;
    let src: Vec<fir::pixels::F32x3> = image
        .as_raw()
        .chunks_exact(3)
        .map(|p| fir::pixels::F32x3::new([p[0], p[1], p[2]].map(f32::from)))
        .collect();
    let fail = |e: String| Error::Image {
        name: "image".into(),
        reason: format!("cannot resize {w}x{h} to {width}x{height}: {e}"),
    };
    let src = fir::images::ImageRef::from_pixels(w, h, &src).map_err(|e| fail(e.to_string()))?;
    let mut dst = fir::images::Image::new(width, height, fir::PixelType::F32x3);
    run_resizer(&src, &mut dst).map_err(|e| fail(e.to_string()))?;
    let typed = dst
        .typed_image::<fir::pixels::F32x3>()
        .ok_or_else(|| fail("the resizer changed the pixel type".into()))?;
    let mut out = RgbImage::new(width, height);
    for (o, p) in out.chunks_exact_mut(3).zip(typed.pixels()) {
        for (o, v) in o.iter_mut().zip(p.0) {
            // `image`'s final step: clamp to 0..=255, round half away from zero (without
            // `round`'s libm call).
            *o = round_half_away_to_u8(v.clamp(0.0, 255.0));
        }
    }
    Ok(Cow::Owned(out))
}

/// Gray, then resized when `size` is given: the preparation of every gray descriptor (HOG,
/// co-occurrence). Errors name the image `image` (batch helpers rename them).
pub fn prepare_gray(image: &DynamicImage, size: Option<(u32, u32)>) -> Result<Cow<'_, GrayImage>> {
    let gray = to_gray(image);
    match size {
        Some((w, h)) if (w, h) != gray.dimensions() => {
            Ok(Cow::Owned(resize_gray(&gray, w, h)?.into_owned()))
        }
        _ => Ok(gray),
    }
}

thread_local! {
    /// One resizer per thread: it keeps its scratch buffers (the intermediate image of the
    /// two-pass convolution) and its CPU-feature choice between calls.
    static RESIZER: RefCell<fir::Resizer> = RefCell::new(fir::Resizer::new());
}

fn buffer_error(width: u32, height: u32) -> Error {
    Error::Image {
        name: "image".into(),
        reason: format!("the resizer returned a buffer too small for {width}x{height}"),
    }
}

fn check_sizes((w, h): (u32, u32), (out_w, out_h): (u32, u32)) -> Result<()> {
    if w == 0 || h == 0 || out_w == 0 || out_h == 0 {
        return Err(Error::Image {
            name: "image".into(),
            reason: format!("cannot resize a {w}x{h} image to {out_w}x{out_h}: both need pixels"),
        });
    }
    Ok(())
}

/// Bilinear (triangle) convolution from `src` into `dst` with this thread's resizer.
fn run_resizer(
    src: &impl fir::IntoImageView,
    dst: &mut fir::images::Image<'_>,
) -> std::result::Result<(), fir::ResizeError> {
    let options = fir::ResizeOptions::new()
        .resize_alg(fir::ResizeAlg::Convolution(fir::FilterType::Bilinear));
    RESIZER.with(|cell| match cell.try_borrow_mut() {
        Ok(mut resizer) => resizer.resize(src, dst, &options),
        // Not reachable (no re-entry), but a fresh resizer is as correct, only slower.
        Err(_) => fir::Resizer::new().resize(src, dst, &options),
    })
}

fn resize_u8(
    pixels: &[u8],
    (w, h): (u32, u32),
    (out_w, out_h): (u32, u32),
    pixel_type: fir::PixelType,
) -> Result<Vec<u8>> {
    check_sizes((w, h), (out_w, out_h))?;
    let fail = |reason: String| Error::Image {
        name: "image".into(),
        reason,
    };
    let src = fir::images::ImageRef::new(w, h, pixels, pixel_type)
        .map_err(|e| fail(format!("{w}x{h} pixel buffer: {e}")))?;
    let mut dst = fir::images::Image::new(out_w, out_h, pixel_type);
    run_resizer(&src, &mut dst)
        .map_err(|e| fail(format!("cannot resize {w}x{h} to {out_w}x{out_h}: {e}")))?;
    Ok(dst.into_vec())
}

#[cfg(test)]
mod tests {
    use super::super::tests::{noisy_rgb, reason};
    use super::*;

    /// The documented tolerance: the SIMD resize is within one grey level of `image`'s
    /// triangle-filter resize at every pixel, when enlarging (HOG's 768x576 -> 1024x768 camera
    /// case, Nordland's 64x32 -> 224x224 CNN stretch) and when shrinking (antialiased).
    #[test]
    fn resize_is_within_one_level_of_image_triangle_filter() {
        use image::imageops::{self, FilterType};
        let cases = [
            ((96, 72), (128, 96)),
            ((64, 32), (224, 224)),
            ((300, 200), (64, 32)),
            ((77, 51), (40, 90)),
            ((5, 3), (1, 1)),
        ];
        for (i, ((w, h), (ow, oh))) in cases.into_iter().enumerate() {
            let rgb = noisy_rgb(w, h, i as u32);
            let gray = DynamicImage::ImageRgb8(rgb.clone()).to_luma8();
            let want_gray = imageops::resize(&gray, ow, oh, FilterType::Triangle);
            let got_gray = resize_gray(&gray, ow, oh).unwrap();
            let want_rgb = imageops::resize(&rgb, ow, oh, FilterType::Triangle);
            let got_rgb = resize_rgb(&rgb, ow, oh).unwrap();
            assert_eq!(got_gray.dimensions(), (ow, oh));
            assert_eq!(got_rgb.dimensions(), (ow, oh));
            for (got, want) in [
                (got_gray.as_raw(), want_gray.as_raw()),
                (got_rgb.as_raw(), want_rgb.as_raw()),
            ] {
                let worst = got
                    .iter()
                    .zip(want)
                    .map(|(a, b)| a.abs_diff(*b))
                    .max()
                    .unwrap();
                assert!(worst <= 1, "{w}x{h} -> {ow}x{oh}: off by {worst} levels");
            }
            // The f32 RGB path rounds once, like `image`. Shrinking (the camera case), only
            // values within float noise of a half level round the other way (at most 1 in
            // 1,000); enlarging, the two libraries place the filter's taps slightly differently
            // at the borders, which moves under 1 % of the values by one level (measured: 1,314
            // of 150,528 for 64x32 -> 224x224).
            let differing = got_rgb
                .as_raw()
                .iter()
                .zip(want_rgb.as_raw())
                .filter(|(a, b)| a != b)
                .count();
            let per_mille = if ow * oh > w * h { 10 } else { 1 };
            assert!(
                differing * 1000 <= per_mille * want_rgb.as_raw().len(),
                "{w}x{h} -> {ow}x{oh}: {differing} RGB values differ"
            );
        }
    }

    #[test]
    fn resize_keeps_images_of_the_right_size_and_rejects_empty_sizes() {
        let gray = DynamicImage::ImageRgb8(noisy_rgb(20, 10, 1)).to_luma8();
        assert!(matches!(
            resize_gray(&gray, 20, 10).unwrap(),
            Cow::Borrowed(_)
        ));
        let (name, why) = reason(resize_gray(&gray, 0, 10).unwrap_err());
        assert_eq!(name, "image");
        assert!(why.contains("20x10 image to 0x10"), "{why}");
        let empty = RgbImage::new(0, 4);
        let (_, why) = reason(resize_rgb(&empty, 8, 8).unwrap_err());
        assert!(why.contains("0x4"), "{why}");
    }

    #[test]
    fn prepare_gray_converts_then_resizes() {
        let rgb = DynamicImage::ImageRgb8(noisy_rgb(50, 30, 9));
        let luma = rgb.to_luma8();
        assert_eq!(*prepare_gray(&rgb, None).unwrap(), luma);
        assert_eq!(*prepare_gray(&rgb, Some((50, 30))).unwrap(), luma);
        assert_eq!(
            *prepare_gray(&rgb, Some((25, 60))).unwrap(),
            *resize_gray(&luma, 25, 60).unwrap()
        );
    }
}
