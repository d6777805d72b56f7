//! Bilinear (triangle) resize of 8-bit gray images when every output pixel reads at most two
//! source pixels per axis (enlarging, the paper's 768x576 -> 1024x768 case): bit for bit the
//! output of `fast_image_resize` 6.1's `Convolution(Bilinear)` for `U8` images, which
//! [`super::image_io::resize_gray`] uses for every other case (shrinking widens the triangle so
//! that it antialiases, and long windows are what that crate is built for).
//!
//! Why: `fast_image_resize`'s 1-channel horizontal pass computes each output pixel as a dot
//! product over a window padded for long filters, then sums it across SIMD lanes; for an
//! enlarging bilinear window (two taps) that is ~2.5 cycles per pixel and was 0.9 ms of the
//! 1.18 ms resize in BENCHMARKS.md ("Image preparation"). Here the two taps of eight output
//! pixels are gathered from one 16-byte load with one byte shuffle (`pshufb`, SSSE3, detected
//! at run time) and weighted with one `pmaddwd` per four pixels.
//!
//! Bit-identity, by construction (and a property test against `fast_image_resize` on random
//! sizes and pixels): the same `f64` weights ([`axis_taps`] follows the crate's
//! `precompute_coefficients` step by step), the same 16-bit fixed point (`Normalizer16`: the
//! largest precision whose doubled largest weight still fits an `i16`, each weight rounded
//! half away from zero), the same integer sums with the same rounding constant and the same
//! clamp to `0..=255`, and the same pass order for 8-bit images: the vertical pass first,
//! rounded to 8 bits, then the horizontal pass. Integer sums are exact, so the order of the
//! two products within a sum does not matter.
//!
//! The one `unsafe` is the call of the SSSE3 row kernel after `is_x86_feature_detected!`
//! has confirmed the CPU has it; the kernel itself builds its vectors from bounds-checked
//! slices with safe intrinsics.

/// The two-tap weights of one axis in 16-bit fixed point: output pixel `i` is
/// `(round + src[start[i]] * k[i][0] + src[start[i] + 1] * k[i][1]) >> precision`, clamped
/// to `0..=255`, where `round = 1 << (precision - 1)`. One-tap outputs have `k[i][1] == 0`,
/// and `start[i] + 1` is always inside the source (one-tap windows at the last pixel are
/// shifted left by one with a leading zero weight), so every output reads two pixels.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct AxisTaps {
    pub(crate) start: Vec<u32>,
    pub(crate) k: Vec<[i16; 2]>,
    pub(crate) precision: u8,
}

/// `fast_image_resize`'s `PRECISION_BITS` (8-bit results with two bits of headroom in `i32`).
const PRECISION_BITS: u8 = 32 - 8 - 2;
/// `fast_image_resize`'s `MAX_COEFFS_PRECISION`: weights are `i16`.
const MAX_COEFFS_PRECISION: u8 = 16 - 1;

/// The weights of resizing an axis of `in_size` pixels to `out_size` with the adaptive
/// triangle filter, or `None` when some output pixel reads more than two source pixels (any
/// real shrinking: the triangle widens to antialias) or the source has fewer than two pixels.
///
/// Follows `fast_image_resize` 6.1 `convolution::precompute_coefficients` (no crop, adaptive
/// kernel, support 1) and `Normalizer16::new` operation for operation, so the weights are the
/// same `f64` and `i16` values.
pub(crate) fn axis_taps(in_size: u32, out_size: u32) -> Option<AxisTaps> {
    if in_size < 2 || out_size == 0 {
        return None;
    }
    let scale = f64::from(in_size) / f64::from(out_size);
    let filter_scale = scale.max(1.0);
    let filter_radius = filter_scale; // support 1.0
    let recip_filter_scale = 1.0 / filter_scale;
    let triangle = |x: f64| {
        let x = x.abs();
        if x < 1.0 {
            1.0 - x
        } else {
            0.0
        }
    };

    let mut bounds: Vec<(u32, Vec<f64>)> = Vec::with_capacity(out_size as usize);
    let mut max_weight = 0.0f64;
    for out_x in 0..out_size {
        let in_center = (f64::from(out_x) + 0.5) * scale;
        let x_min = (in_center - filter_radius).floor().max(0.) as u32;
        let x_max = (in_center + filter_radius).ceil().min(f64::from(in_size)) as u32;
        let center = in_center - 0.5;
        let mut start = x_min;
        let mut weights = Vec::with_capacity(3);
        let mut sum = 0.0f64;
        for x in x_min..x_max {
            let w = triangle((f64::from(x) - center) * recip_filter_scale);
            if x == start && w == 0. {
                start += 1;
            } else {
                weights.push(w);
                sum += w;
            }
        }
        while weights.last() == Some(&0.0) {
            weights.pop();
        }
        if sum != 0.0 {
            weights.iter_mut().for_each(|w| *w /= sum);
        }
        if weights.len() > 2 {
            return None;
        }
        max_weight = weights.iter().copied().fold(max_weight, f64::max);
        bounds.push((start, weights));
    }

    // `Normalizer16::new`: the largest precision whose doubled largest weight fits an i16.
    let mut precision = 0u8;
    for cur in 0..PRECISION_BITS {
        precision = cur;
        let next = (max_weight * f64::from(1u32 << (precision + 1))).round() as i32;
        if next >= (1 << MAX_COEFFS_PRECISION) {
            break;
        }
    }
    if precision < 1 {
        return None;
    }
    let fixed = f64::from(1u32 << precision);
    let to_i16 = |w: f64| (w * fixed).round() as i16;

    let mut start = Vec::with_capacity(bounds.len());
    let mut k = Vec::with_capacity(bounds.len());
    for (s, weights) in bounds {
        let (s, pair) = match weights[..] {
            [a, b] => (s, [to_i16(a), to_i16(b)]),
            // One tap (the window sits exactly on a pixel, or at an edge): pad to two, on the
            // side that stays inside the source.
            [a] if s + 1 < in_size => (s, [to_i16(a), 0]),
            [a] => (s - 1, [0, to_i16(a)]),
            // An all-zero window cannot happen with a support of 1; stay exact anyway.
            _ => (s.min(in_size - 2), [0, 0]),
        };
        start.push(s);
        k.push(pair);
    }
    Some(AxisTaps {
        start,
        k,
        precision,
    })
}

/// `fast_image_resize`'s clamp of one fixed-point sum to a pixel.
#[inline(always)]
fn clip(sum: i32, precision: u8) -> u8 {
    (sum >> precision).clamp(0, 255) as u8
}

/// The bilinear resize of the `w x h` gray `src` to `out_w x out_h`, or `None` when an axis
/// needs more than two taps (see [`axis_taps`]); then the caller uses `fast_image_resize`.
/// Bit-identical to `fast_image_resize` (module doc). An axis whose size does not change is
/// copied, as that crate skips its pass.
pub(crate) fn resize_gray_2tap(
    src: &[u8],
    (w, h): (u32, u32),
    (out_w, out_h): (u32, u32),
) -> Option<Vec<u8>> {
    resize_with(src, (w, h), (out_w, out_h), Kernel::detect())
}

/// Which horizontal row kernel runs (tests force the portable one).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kernel {
    Portable,
    #[cfg(target_arch = "x86_64")]
    Ssse3,
}

impl Kernel {
    fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("ssse3") {
            return Kernel::Ssse3;
        }
        Kernel::Portable
    }
}

fn resize_with(
    src: &[u8],
    (w, h): (u32, u32),
    (out_w, out_h): (u32, u32),
    kernel: Kernel,
) -> Option<Vec<u8>> {
    let (w, h, out_w, out_h) = (w as usize, h as usize, out_w as usize, out_h as usize);
    if src.len() != w.checked_mul(h)? || out_w == 0 || out_h == 0 {
        return None;
    }
    // `None` = the axis keeps its size (no pass, as in `fast_image_resize`).
    let horizontal = match w == out_w {
        true => None,
        false => Some(axis_taps(w as u32, out_w as u32)?),
    };
    let vertical = match h == out_h {
        true => None,
        false => Some(axis_taps(h as u32, out_h as u32)?),
    };
    let mut out = vec![0u8; out_w.checked_mul(out_h)?];
    let row_plan = horizontal
        .as_ref()
        .map(|taps| RowPlan::new(taps, w, kernel));
    let mut column = vec![0u8; if vertical.is_some() { w } else { 0 }];
    for (y, out_row) in out.chunks_exact_mut(out_w).enumerate() {
        // The vertical pass first (rounded to 8 bits), as `fast_image_resize` does for u8.
        let row: &[u8] = match &vertical {
            Some(taps) => {
                let r0 = taps.start[y] as usize * w;
                let (a, b) = (&src[r0..r0 + w], &src[r0 + w..r0 + 2 * w]);
                vertical_row(a, b, taps.k[y], taps.precision, &mut column);
                &column
            }
            None => &src[y * w..(y + 1) * w],
        };
        match &row_plan {
            Some(plan) => plan.run(row, out_row),
            None => out_row.copy_from_slice(row),
        }
    }
    Some(out)
}

/// One row of the vertical pass: `out[x] = clip(round + a[x] k0 + b[x] k1)`; plain code that
/// the compiler vectorises (SSE2 `pmaddwd`-style multiply-adds on the baseline build).
fn vertical_row(a: &[u8], b: &[u8], [k0, k1]: [i16; 2], precision: u8, out: &mut [u8]) {
    let round = 1i32 << (precision - 1);
    let (k0, k1) = (i32::from(k0), i32::from(k1));
    for ((o, &a), &b) in out.iter_mut().zip(a).zip(b) {
        *o = clip(round + i32::from(a) * k0 + i32::from(b) * k1, precision);
    }
}

/// The horizontal pass of one axis, prepared once per image for the chosen kernel.
struct RowPlan<'a> {
    taps: &'a AxisTaps,
    #[cfg(target_arch = "x86_64")]
    blocks: Option<ssse3::Blocks>,
}

impl<'a> RowPlan<'a> {
    fn new(taps: &'a AxisTaps, in_width: usize, kernel: Kernel) -> Self {
        #[cfg(not(target_arch = "x86_64"))]
        let _ = (in_width, kernel);
        RowPlan {
            taps,
            #[cfg(target_arch = "x86_64")]
            blocks: (kernel == Kernel::Ssse3).then(|| ssse3::Blocks::new(taps, in_width)),
        }
    }

    fn run(&self, row: &[u8], out: &mut [u8]) {
        #[cfg(target_arch = "x86_64")]
        if let Some(blocks) = &self.blocks {
            let done = blocks.run(row, out);
            horizontal_portable(self.taps, row, out, done);
            return;
        }
        horizontal_portable(self.taps, row, out, 0);
    }
}

/// The horizontal pass of output pixels `from..` of one row, one pixel at a time.
fn horizontal_portable(taps: &AxisTaps, row: &[u8], out: &mut [u8], from: usize) {
    let round = 1i32 << (taps.precision - 1);
    let pixels = out.iter_mut().zip(&taps.start).zip(&taps.k).skip(from);
    for ((o, &s), &[k0, k1]) in pixels {
        let s = s as usize;
        let sum = round + i32::from(row[s]) * i32::from(k0) + i32::from(row[s + 1]) * i32::from(k1);
        *o = clip(sum, taps.precision);
    }
}

#[cfg(target_arch = "x86_64")]
mod ssse3 {
    //! The SSSE3 horizontal pass: eight output pixels per step, their 16 taps gathered from
    //! one 16-byte load by `pshufb` (as 16-bit lanes) and weighted by two `pmaddwd`.

    use std::arch::x86_64::*;

    use super::AxisTaps;

    /// Per block of eight output pixels: where its 16-byte load starts, the two shuffle
    /// masks (taps of pixels 0-3 and 4-7 as zero-extended 16-bit lanes) and the weights in
    /// the same lane order.
    struct Block {
        load: usize,
        masks: [[u8; 16]; 2],
        weights: [[i16; 8]; 2],
    }

    /// The blocks of one axis: the first `8 * blocks.len()` output pixels; the rest (a block
    /// whose load would run past the row, or whose taps do not fit 16 bytes) is left to the
    /// portable loop.
    pub(super) struct Blocks {
        blocks: Vec<Block>,
        round: i32,
        precision: i32,
    }

    impl Blocks {
        pub(super) fn new(taps: &AxisTaps, in_width: usize) -> Self {
            let mut blocks = Vec::with_capacity(taps.start.len() / 8);
            for (starts, k) in taps.start.chunks_exact(8).zip(taps.k.chunks_exact(8)) {
                let load = starts[0] as usize;
                let fits = starts.iter().all(|&s| s as usize + 1 - load < 16);
                if !fits || load + 16 > in_width {
                    break;
                }
                let mut masks = [[0x80u8; 16]; 2];
                let mut weights = [[0i16; 8]; 2];
                for (i, (&s, &[k0, k1])) in starts.iter().zip(k).enumerate() {
                    let o = (s as usize - load) as u8;
                    let (half, lane) = (i / 4, i % 4);
                    masks[half][4 * lane] = o;
                    masks[half][4 * lane + 2] = o + 1;
                    weights[half][2 * lane] = k0;
                    weights[half][2 * lane + 1] = k1;
                }
                blocks.push(Block {
                    load,
                    masks,
                    weights,
                });
            }
            Blocks {
                blocks,
                round: 1 << (taps.precision - 1),
                precision: i32::from(taps.precision),
            }
        }

        /// Fills the first `8 * blocks` pixels of `out` from `row`; returns how many.
        pub(super) fn run(&self, row: &[u8], out: &mut [u8]) -> usize {
            // SAFETY: `Blocks` is only built when `Kernel::detect` found SSSE3 on this CPU
            // (`RowPlan::new`), the one precondition of this `target_feature` function.
            #[allow(unsafe_code)]
            unsafe {
                self.run_ssse3(row, out)
            }
        }

        #[target_feature(enable = "ssse3")]
        fn run_ssse3(&self, row: &[u8], out: &mut [u8]) -> usize {
            let round = _mm_set1_epi32(self.round);
            let shift = _mm_cvtsi32_si128(self.precision);
            for (block, out) in self.blocks.iter().zip(out.chunks_exact_mut(8)) {
                let pixels = bytes16(&row[block.load..block.load + 16]);
                let lo = _mm_shuffle_epi8(pixels, bytes16(&block.masks[0]));
                let hi = _mm_shuffle_epi8(pixels, bytes16(&block.masks[1]));
                let lo = _mm_madd_epi16(lo, words8(&block.weights[0]));
                let hi = _mm_madd_epi16(hi, words8(&block.weights[1]));
                let lo = _mm_sra_epi32(_mm_add_epi32(lo, round), shift);
                let hi = _mm_sra_epi32(_mm_add_epi32(hi, round), shift);
                // Signed saturation to i16, then unsigned to u8: the clamp to 0..=255.
                let words = _mm_packs_epi32(lo, hi);
                let bytes = _mm_packus_epi16(words, words);
                out.copy_from_slice(&_mm_cvtsi128_si64(bytes).to_le_bytes());
            }
            8 * self.blocks.len().min(out.len() / 8)
        }
    }

    /// Sixteen bytes as a vector (little-endian lanes); compiles to one unaligned load.
    #[inline]
    #[target_feature(enable = "sse2")]
    fn bytes16(b: &[u8]) -> __m128i {
        let lo = i64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]);
        let hi = i64::from_le_bytes([b[8], b[9], b[10], b[11], b[12], b[13], b[14], b[15]]);
        _mm_set_epi64x(hi, lo)
    }

    /// Eight `i16` as a vector.
    #[inline]
    #[target_feature(enable = "sse2")]
    fn words8(w: &[i16; 8]) -> __m128i {
        _mm_setr_epi16(w[0], w[1], w[2], w[3], w[4], w[5], w[6], w[7])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fast_image_resize as fir;
    use proptest::prelude::*;

    /// The reference: `fast_image_resize`'s bilinear convolution of a U8 image.
    fn reference(src: &[u8], (w, h): (u32, u32), (out_w, out_h): (u32, u32)) -> Vec<u8> {
        let src = fir::images::ImageRef::new(w, h, src, fir::PixelType::U8).unwrap();
        let mut dst = fir::images::Image::new(out_w, out_h, fir::PixelType::U8);
        let options = fir::ResizeOptions::new()
            .resize_alg(fir::ResizeAlg::Convolution(fir::FilterType::Bilinear));
        fir::Resizer::new()
            .resize(&src, &mut dst, &options)
            .unwrap();
        dst.into_vec()
    }

    fn pixels(w: u32, h: u32, seed: u64) -> Vec<u8> {
        let mut s = seed | 1;
        (0..w * h)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s >> 24) as u8
            })
            .collect()
    }

    fn kernels() -> Vec<Kernel> {
        let detected = Kernel::detect();
        let mut all = vec![Kernel::Portable];
        if detected != Kernel::Portable {
            all.push(detected);
        }
        all
    }

    #[test]
    fn the_paper_case_is_bit_identical_to_fast_image_resize_on_every_kernel() {
        let src = pixels(768, 576, 7);
        let want = reference(&src, (768, 576), (1024, 768));
        for kernel in kernels() {
            let got = resize_with(&src, (768, 576), (1024, 768), kernel).expect("2 taps");
            assert!(got == want, "{kernel:?} differs from fast_image_resize");
        }
    }

    #[test]
    fn extreme_pixels_saturate_like_fast_image_resize() {
        // Black/white edges push sums to the ends of the range.
        let src: Vec<u8> = (0..40 * 30)
            .map(|i| if (i / 3) % 2 == 0 { 0 } else { 255 })
            .collect();
        for out in [(41, 31), (80, 60), (123, 97), (40, 64), (77, 30)] {
            let want = reference(&src, (40, 30), out);
            for kernel in kernels() {
                assert_eq!(resize_with(&src, (40, 30), out, kernel), Some(want.clone()));
            }
        }
    }

    #[test]
    fn shrinking_or_tiny_sources_are_left_to_fast_image_resize() {
        assert!(axis_taps(100, 50).is_none(), "shrinking widens the window");
        // Shrinking by one pixel in a thousand: the triangle is 2 + 2/999 px wide, and its
        // third tap weighs nothing at these positions; declined or not, the output is
        // fast_image_resize's.
        let wide = pixels(1000, 3, 5);
        if let Some(got) = resize_gray_2tap(&wide, (1000, 3), (999, 3)) {
            assert!(got == reference(&wide, (1000, 3), (999, 3)));
        }
        assert!(axis_taps(1, 10).is_none(), "one source pixel");
        assert!(axis_taps(2, 3).is_some());
        let src = pixels(10, 10, 3);
        // A slight shrink can still read two pixels per output: accepted only bit for bit.
        for out in [(9, 20), (20, 9)] {
            if let Some(got) = resize_gray_2tap(&src, (10, 10), out) {
                assert!(got == reference(&src, (10, 10), out), "{out:?}");
            }
        }
        assert_eq!(
            resize_gray_2tap(&src, (10, 9), (20, 20)),
            None,
            "wrong buffer size"
        );
    }

    #[test]
    fn enlarging_weights_have_two_taps_inside_the_source() {
        for (n, m) in [
            (2, 3),
            (3, 1000),
            (768, 1024),
            (576, 768),
            (5, 10),
            (7, 7 * 4),
        ] {
            let taps = axis_taps(n, m).expect("enlarging has at most two taps");
            assert_eq!(taps.start.len(), m as usize);
            assert!(taps.start.iter().all(|&s| s + 1 < n));
            // Each pair sums to 1 in fixed point, up to the rounding of each weight.
            let one = 1i32 << taps.precision;
            for [a, b] in &taps.k {
                assert!((i32::from(*a) + i32::from(*b) - one).abs() <= 1);
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]

        /// Random sizes (each axis enlarged or kept) and pixels: bit for bit
        /// `fast_image_resize`, with the portable and the detected kernel.
        #[test]
        fn bit_identical_to_fast_image_resize(
            w in 2u32..90,
            h in 2u32..60,
            grow_w in 0u32..200,
            grow_h in 0u32..120,
            seed in any::<u64>(),
        ) {
            let (out_w, out_h) = (w + grow_w, h + grow_h);
            let src = pixels(w, h, seed);
            let want = reference(&src, (w, h), (out_w, out_h));
            for kernel in kernels() {
                let got = resize_with(&src, (w, h), (out_w, out_h), kernel);
                prop_assert!(got.as_ref() == Some(&want), "{kernel:?} {w}x{h} -> {out_w}x{out_h}");
            }
        }

        /// Any sizes, shrinking included: either left to `fast_image_resize` (`None`) or
        /// bit for bit its output.
        #[test]
        fn any_size_is_declined_or_bit_identical(
            w in 2u32..120,
            h in 2u32..80,
            out_w in 1u32..200,
            out_h in 1u32..140,
            seed in any::<u64>(),
        ) {
            let src = pixels(w, h, seed);
            for kernel in kernels() {
                if let Some(got) = resize_with(&src, (w, h), (out_w, out_h), kernel) {
                    let want = reference(&src, (w, h), (out_w, out_h));
                    prop_assert!(got == want, "{kernel:?} {w}x{h} -> {out_w}x{out_h}");
                }
            }
        }
    }
}
