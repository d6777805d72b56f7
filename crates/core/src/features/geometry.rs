//! Input geometry: the one rule that brings an image of any size to the pixel size a map's
//! descriptor was built for.
//!
//! A global descriptor is only comparable with descriptors of the same *input geometry*: for
//! HOG the cell grid, i.e. the pixel size the image has when the grid is laid (the map's
//! `resize`, or else the size of its first image); for the CNN the network input (the CNN's own
//! `CnnResize` handles that). Cameras differ, so a query or trip frame of another size or aspect
//! ratio must be brought to the map's geometry instead of being refused.
//!
//! The rule ([`fit_image`]), applied to every image (references and queries alike, so an image
//! that already has the geometry is untouched and its descriptor bit-identical to before):
//! 1. [`Fit::Stretch`] (the default): resize the whole frame to the geometry (bilinear, the
//!    shared [`super::resize_gray`] path). It keeps the full field of view, as `eval`'s CNN
//!    default `--cnn-resize stretch`; for a camera of the same aspect ratio (Gardens Point's night 640x360 against
//!    day 960x540) it is the only sensible choice and the two fits are identical.
//! 2. [`Fit::Crop`]: first cut the centred window of the geometry's aspect ratio out of the
//!    frame ([`crop_window`]), then resize as above. It keeps the
//!    scene undistorted when the other camera sees *more* on one axis with the same lens.
//!
//! [`Fitted`] wraps an extractor with this rule; its descriptor length no longer depends on
//! the input size. Absurd sizes still fail: an image with no pixels, or a crop window smaller
//! than one pixel, is an [`Error::Image`]; the decoder's pixel limit stays the guard against
//! huge images.

use std::borrow::Cow;
use std::str::FromStr;

use image::DynamicImage;

use super::Extractor;
use crate::{Error, Result};

/// How an image of another aspect ratio reaches the input geometry.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Fit {
    /// Resize the whole frame (keeps the field of view, distorts a different aspect ratio).
    #[default]
    Stretch,
    /// Cut the centred window of the geometry's aspect ratio, then resize (keeps the shapes).
    Crop,
}

impl Fit {
    /// The name used by the CLI and the HTTP API (`stretch`, `crop`).
    pub fn name(self) -> &'static str {
        match self {
            Fit::Stretch => "stretch",
            Fit::Crop => "crop",
        }
    }
}

impl FromStr for Fit {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        match s {
            "stretch" => Ok(Fit::Stretch),
            "crop" => Ok(Fit::Crop),
            other => Err(Error::param(
                "fit",
                format!("expected `stretch` or `crop`, got `{other}`"),
            )),
        }
    }
}

/// The centred window `(x, y, width, height)` of `image_size` that has the aspect ratio of
/// `geometry` (its side rounded to the nearest pixel); the whole image when that rounds to it.
pub fn crop_window(image_size: (u32, u32), geometry: (u32, u32)) -> Result<(u32, u32, u32, u32)> {
    let (w, h) = image_size;
    let (gw, gh) = geometry;
    if w == 0 || h == 0 || gw == 0 || gh == 0 {
        return Err(Error::Image {
            name: "input".into(),
            reason: format!("cannot fit a {w}x{h} px image to {gw}x{gh} px: both need pixels"),
        });
    }
    // Width of the window of full height, and height of the window of full width, rounded.
    let (w64, h64, gw64, gh64) = (u64::from(w), u64::from(h), u64::from(gw), u64::from(gh));
    let width_at_full_height = (h64 * gw64 + gh64 / 2) / gh64;
    let height_at_full_width = (w64 * gh64 + gw64 / 2) / gw64;
    let (cw, ch) = if width_at_full_height < w64 {
        (width_at_full_height, h64)
    } else if height_at_full_width < h64 {
        (w64, height_at_full_width)
    } else {
        (w64, h64)
    };
    if cw == 0 || ch == 0 {
        return Err(Error::Image {
            name: "input".into(),
            reason: format!(
                "a {w}x{h} px image has no {gw}:{gh} window of at least one pixel to crop"
            ),
        });
    }
    // Both fit in u32: they are at most w and h.
    let (cw, ch) = (cw as u32, ch as u32);
    Ok(((w - cw) / 2, (h - ch) / 2, cw, ch))
}

/// The pixel size `(width, height)` of an image file as it decodes (upright, after its Exif
/// orientation), read from its header only.
pub fn image_file_size(path: &std::path::Path) -> Result<(u32, u32)> {
    let reader = image::ImageReader::open(path)
        .map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?
        .with_guessed_format()
        .map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
    super::upright_dimensions(reader).map_err(|e| Error::Image {
        name: path.display().to_string(),
        reason: format!("cannot read the image header: {e}"),
    })
}

/// `image` cropped as [`Fit`] asks for the geometry `geometry` (not yet resized: the
/// extractor resizes, on the gray or RGB image it needs). Borrowed when nothing is cut.
pub fn fit_image(
    image: &DynamicImage,
    geometry: (u32, u32),
    fit: Fit,
) -> Result<Cow<'_, DynamicImage>> {
    let size = (image.width(), image.height());
    let (x, y, cw, ch) = crop_window(size, geometry)?;
    if fit == Fit::Stretch || (cw, ch) == size {
        return Ok(Cow::Borrowed(image));
    }
    Ok(Cow::Owned(image.crop_imm(x, y, cw, ch)))
}

/// An extractor that first brings every image to one input geometry by the [`Fit`] rule.
///
/// The inner extractor must resize to `geometry` itself (e.g. HOG with `resize: Some(geometry)`)
/// so that the resize runs on the representation it needs; [`Fitted::hog`] builds that.
pub struct Fitted<E> {
    inner: E,
    geometry: (u32, u32),
    fit: Fit,
}

impl<E: Extractor> Fitted<E> {
    /// Wraps `inner`, which resizes to `geometry`.
    pub fn new(inner: E, geometry: (u32, u32), fit: Fit) -> Self {
        Fitted {
            inner,
            geometry,
            fit,
        }
    }

    /// The input geometry `(width, height)`.
    pub fn geometry(&self) -> (u32, u32) {
        self.geometry
    }

    /// The fit rule.
    pub fn fit(&self) -> Fit {
        self.fit
    }
}

impl Fitted<super::hog::HogSpec> {
    /// HOG with `cell_size` px cells on images brought to `geometry` by `fit`.
    pub fn hog(cell_size: u32, geometry: (u32, u32), fit: Fit) -> Result<Self> {
        let spec = super::hog::HogSpec::new(super::hog::HogOptions {
            cell_size,
            resize: Some(geometry),
        })?;
        Ok(Fitted::new(spec, geometry, fit))
    }
}

impl<E: Extractor> Extractor for Fitted<E> {
    fn dim_for(&self, width: u32, height: u32) -> Result<usize> {
        crop_window((width, height), self.geometry)?;
        let (gw, gh) = self.geometry;
        self.inner.dim_for(gw, gh)
    }

    fn extract(&self, image: &DynamicImage) -> Result<Vec<f32>> {
        let fitted = fit_image(image, self.geometry, self.fit)?;
        self.inner.extract(&fitted)
    }

    fn pixels(&self) -> super::Pixels {
        self.inner.pixels()
    }
}

#[cfg(test)]
mod tests {
    use super::super::hog::{HogOptions, HogSpec};
    use super::*;
    use image::{GrayImage, Luma};

    fn textured(w: u32, h: u32) -> DynamicImage {
        DynamicImage::ImageLuma8(GrayImage::from_fn(w, h, |x, y| {
            Luma([((x * x + 7 * y + x * y * 3) % 251) as u8])
        }))
    }

    #[test]
    fn crop_window_keeps_the_geometry_aspect_ratio_centred() {
        // Same ratio (16:9 vs 16:9): nothing is cut.
        assert_eq!(
            crop_window((640, 360), (960, 540)).unwrap(),
            (0, 0, 640, 360)
        );
        // 4:3 into 16:9: full width, centred 16:9 band.
        assert_eq!(
            crop_window((640, 480), (960, 540)).unwrap(),
            (0, 60, 640, 360)
        );
        // 16:9 into 4:3: full height, centred 4:3 window.
        assert_eq!(
            crop_window((960, 540), (640, 480)).unwrap(),
            (120, 0, 720, 540)
        );
        // Off by one pixel: that pixel is cut (the left half of the margin rounds down).
        assert_eq!(
            crop_window((641, 360), (960, 540)).unwrap(),
            (0, 0, 640, 360)
        );
        // Off by less than half a pixel: the whole image.
        assert_eq!(
            crop_window((1282, 721), (16, 9)).unwrap(),
            (0, 0, 1282, 721)
        );
        assert!(crop_window((0, 10), (4, 4)).is_err());
        assert!(crop_window((10, 10), (0, 4)).is_err());
        // A 1 px high strip has no 1:1000 window a whole pixel wide.
        assert!(crop_window((1000, 1), (1, 1000)).is_err());
    }

    #[test]
    fn an_image_of_the_geometry_is_untouched() {
        let img = textured(64, 32);
        let plain = HogSpec::new(HogOptions {
            cell_size: 8,
            resize: None,
        })
        .unwrap();
        for fit in [Fit::Stretch, Fit::Crop] {
            let fitted = Fitted::hog(8, (64, 32), fit).unwrap();
            assert_eq!(
                fitted.extract(&img).unwrap(),
                plain.extract(&img).unwrap(),
                "{fit:?}"
            );
        }
    }

    #[test]
    fn any_size_gives_the_geometry_descriptor() {
        let fitted = Fitted::hog(8, (64, 32), Fit::Stretch).unwrap();
        let dim = fitted.dim_for(64, 32).unwrap();
        for (w, h) in [(32, 16), (128, 64), (50, 50), (8, 9), (640, 360)] {
            assert_eq!(fitted.dim_for(w, h).unwrap(), dim);
            assert_eq!(fitted.extract(&textured(w, h)).unwrap().len(), dim);
        }
        // Less than one cell of detail is not stretched to the geometry (issue 14: a clear
        // error instead of a descriptor of upscaled nothing).
        assert!(matches!(
            fitted.extract(&textured(3, 7)),
            Err(Error::Image { .. })
        ));
        // Stretch of a 2x image is the HOG of its resize; crop cuts first.
        let big = textured(128, 80);
        let stretched = HogSpec::new(HogOptions {
            cell_size: 8,
            resize: Some((64, 32)),
        })
        .unwrap()
        .extract(&big)
        .unwrap();
        assert_eq!(fitted.extract(&big).unwrap(), stretched);
        let cropped = Fitted::hog(8, (64, 32), Fit::Crop).unwrap();
        let window = big.crop_imm(0, 8, 128, 64);
        assert_eq!(
            cropped.extract(&big).unwrap(),
            fitted.extract(&window).unwrap()
        );
        assert_ne!(cropped.extract(&big).unwrap(), stretched);
    }

    #[test]
    fn empty_images_and_bad_fits_are_errors() {
        let fitted = Fitted::hog(8, (64, 32), Fit::Crop).unwrap();
        assert!(matches!(fitted.dim_for(0, 5), Err(Error::Image { .. })));
        let tall = Fitted::hog(8, (8, 1000), Fit::Crop).unwrap();
        assert!(matches!(
            tall.extract(&textured(1000, 1)),
            Err(Error::Image { .. })
        ));
        assert_eq!("crop".parse::<Fit>().unwrap(), Fit::Crop);
        assert_eq!("stretch".parse::<Fit>().unwrap(), Fit::Stretch);
        assert!("zoom".parse::<Fit>().is_err());
        // A geometry smaller than one cell is refused up front.
        assert!(Fitted::hog(8, (4, 32), Fit::Stretch).is_err());
    }
}
