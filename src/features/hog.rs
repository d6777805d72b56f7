//! HOG global descriptor (placeholder, replaced by the features work).
use crate::Result;

/// User-facing HOG settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HogOptions {
    /// Side of a square cell in pixels (default 32, the paper's).
    pub cell_size: u32,
    /// Optional resize to `(width, height)` before extraction.
    pub resize: Option<(u32, u32)>,
}

impl Default for HogOptions {
    fn default() -> Self {
        HogOptions {
            cell_size: 32,
            resize: None,
        }
    }
}

/// Validated HOG settings; implements [`super::Extractor`].
#[derive(Clone, Debug, PartialEq)]
pub struct HogSpec {
    options: HogOptions,
}

impl HogSpec {
    /// Validates `options`.
    pub fn new(options: HogOptions) -> Result<Self> {
        Ok(HogSpec { options })
    }
}

impl super::Extractor for HogSpec {
    fn dim_for(&self, _width: u32, _height: u32) -> Result<usize> {
        todo!("{:?}", self.options)
    }
    fn extract(&self, _image: &image::DynamicImage) -> Result<Vec<f32>> {
        todo!()
    }
}
