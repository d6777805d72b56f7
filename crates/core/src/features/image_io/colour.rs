//! Colour conversion of decoded images: [`to_gray`] (`image`'s Rec. 709 `to_luma8` bit for bit,
//! in one branch-free loop over RGB8) and [`to_rgb`]; plus the half-away rounding to 8 bits
//! that the RGB resize shares. Kept apart because its bit-identity with `image` is its own
//! contract, with its own exhaustive tests.

use std::borrow::Cow;

use image::{DynamicImage, GrayImage, RgbImage};

/// 8-bit luma of any decoded image: Rec. 709 weights, exactly `image`'s `to_luma8`; borrowed
/// when the image is already 8-bit gray.
pub fn to_gray(image: &DynamicImage) -> Cow<'_, GrayImage> {
    match image {
        DynamicImage::ImageLuma8(gray) => Cow::Borrowed(gray),
        DynamicImage::ImageRgb8(rgb) => Cow::Owned(rgb_to_luma(rgb)),
        // Rare layouts (alpha, 16 bit, float) keep the generic conversion.
        other => Cow::Owned(other.to_luma8()),
    }
}

/// 8-bit RGB of any decoded image (gray replicated, alpha dropped); borrowed when the image is
/// already RGB8.
pub fn to_rgb(image: &DynamicImage) -> Cow<'_, RgbImage> {
    match image.as_rgb8() {
        Some(rgb) => Cow::Borrowed(rgb),
        None => Cow::Owned(image.to_rgb8()),
    }
}

/// Rec. 709 luma weights as `image` 0.25 derives them (the Y row of the BT.709 RGB -> XYZ
/// matrix for D65, computed by `moxcms`), bit for bit.
const LUMA_WEIGHTS: [f32; 3] = [
    f32::from_bits(0x3e59_c05b), // 0.21264784
    f32::from_bits(0x3f37_15fc), // 0.7151792
    f32::from_bits(0x3d93_cf75), // 0.07217304
];

/// `image`'s 8-bit luma (`to_luma8`) of an RGB8 image, bit for bit: each channel scaled to
/// `0..=1` in `f32`, weighted and summed in the same order, then `round(255 * y)` (half away
/// from zero). `image` runs this through a generic per-pixel path with a libm `roundf` call;
/// here it is one branch-free loop (the rounding is done with selects, which SSE2 has).
/// A test compares all 2^24 RGB values with `to_luma8`.
fn rgb_to_luma(rgb: &RgbImage) -> GrayImage {
    /// Pixels per block: fixed-size arrays let the compiler turn the strided RGB loads and the
    /// arithmetic into vector code (a plain per-pixel loop stays scalar).
    const BLOCK: usize = 16;
    let (w, h) = rgb.dimensions();
    let mut gray = GrayImage::new(w, h);
    let out: &mut [u8] = &mut gray;
    let src = rgb.as_raw();
    let mut out_blocks = out.chunks_exact_mut(BLOCK);
    let mut src_blocks = src.chunks_exact(3 * BLOCK);
    for (o, px) in (&mut out_blocks).zip(&mut src_blocks) {
        let mut y = [0.0f32; BLOCK];
        for (i, y) in y.iter_mut().enumerate() {
            *y = luma_f32(px[3 * i], px[3 * i + 1], px[3 * i + 2]);
        }
        for (o, y) in o.iter_mut().zip(y) {
            *o = round_half_away_to_u8(y);
        }
    }
    for (o, px) in out_blocks
        .into_remainder()
        .iter_mut()
        .zip(src_blocks.remainder().chunks_exact(3))
    {
        *o = round_half_away_to_u8(luma_f32(px[0], px[1], px[2]));
    }
    gray
}

/// `255 y` of one pixel, with `image`'s operations in `image`'s order.
#[inline(always)]
fn luma_f32(r: u8, g: u8, b: u8) -> f32 {
    const SCALE: f32 = 1.0 / 255.0;
    let [kr, kg, kb] = LUMA_WEIGHTS;
    (f32::from(r) * SCALE * kr + f32::from(g) * SCALE * kg + f32::from(b) * SCALE * kb) * 255.0
}

/// `x.round() as u8` for `0 <= x <= 255.5`, without a libm call or a saturating conversion:
/// `2^23` added and removed rounds to nearest-even, the compare turns that into `floor`, the
/// fraction decides the half, and the integer is read from the mantissa of `2^23 + n` (all
/// selects and bit operations, which SSE2 has).
#[inline(always)]
pub(super) fn round_half_away_to_u8(x: f32) -> u8 {
    const MAGIC: f32 = 8_388_608.0; // 2^23
    let nearest = (x + MAGIC) - MAGIC;
    let floor = if nearest > x { nearest - 1.0 } else { nearest };
    let rounded = if x - floor >= 0.5 { floor + 1.0 } else { floor };
    // The weights sum to 1.0000002, so white gives 255.00005 -> 255; the min is a safeguard.
    // For an integer n < 2^23, the low mantissa bits of 2^23 + n are n.
    ((rounded.min(255.0) + MAGIC).to_bits() & 0xff) as u8
}

#[cfg(test)]
mod tests {
    use super::super::tests::noisy_rgb;
    use super::*;
    use image::Rgb;

    /// `resize_rgb` rounds its filtered `f32` values (clamped to 0..=255) with
    /// `round_half_away_to_u8` instead of `f32::round`: the same byte for every `f32` in that
    /// range (checked once for all 1.13e9 of them; here every 61st bit pattern, every half and
    /// both neighbours of every half).
    #[test]
    fn round_half_away_to_u8_is_round_on_0_to_255() {
        let check = |x: f32| assert_eq!(round_half_away_to_u8(x), x.round() as u8, "{x}");
        for bits in (0..=255.0f32.to_bits()).step_by(61) {
            check(f32::from_bits(bits));
        }
        for n in 0..=510u16 {
            let half = f32::from(n) / 2.0;
            check(half);
            check(f32::from_bits(half.to_bits() + 1).min(255.0));
            if half > 0.0 {
                check(f32::from_bits(half.to_bits() - 1));
            }
        }
        check(-0.0);
    }

    #[test]
    fn to_gray_is_image_to_luma8_for_every_rgb_value() {
        // All 2^24 colours, as a 4096x4096 image.
        let all = RgbImage::from_fn(4096, 4096, |x, y| {
            let v = y * 4096 + x;
            Rgb([(v >> 16) as u8, (v >> 8) as u8, v as u8])
        });
        let all = DynamicImage::ImageRgb8(all);
        let want = all.to_luma8();
        let got = to_gray(&all);
        if let Some(i) = got
            .as_raw()
            .iter()
            .zip(want.as_raw())
            .position(|(a, b)| a != b)
        {
            panic!(
                "colour {:#08x}: to_gray {} != to_luma8 {}",
                i,
                got.as_raw()[i],
                want.as_raw()[i]
            );
        }
    }

    #[test]
    fn to_gray_is_image_to_luma8_bit_for_bit() {
        let rgb = noisy_rgb(97, 41, 3);
        let dynamic = DynamicImage::ImageRgb8(rgb.clone());
        assert_eq!(*to_gray(&dynamic), dynamic.to_luma8());
        // Every extreme of the weights: pure channels and white.
        let corners = RgbImage::from_fn(4, 1, |x, _| match x {
            0 => Rgb([255, 0, 0]),
            1 => Rgb([0, 255, 0]),
            2 => Rgb([0, 0, 255]),
            _ => Rgb([255, 255, 255]),
        });
        let corners = DynamicImage::ImageRgb8(corners);
        assert_eq!(*to_gray(&corners), corners.to_luma8());
        // Gray input is borrowed, other layouts use the generic conversion.
        let gray = DynamicImage::ImageLuma8(dynamic.to_luma8());
        assert!(matches!(to_gray(&gray), Cow::Borrowed(_)));
        let rgba = DynamicImage::ImageRgba8(dynamic.to_rgba8());
        assert_eq!(*to_gray(&rgba), dynamic.to_luma8());
    }
}
