//! Global image descriptors: the [`Extractor`] trait, image decoding, and batch extraction
//! across cores.
//!
//! An extractor turns one decoded image into one global descriptor vector. Its length depends
//! only on the extractor's validated settings and the image size (after any resize the settings
//! ask for), so a map's descriptors are comparable with each other.

use crate::{Matrix, Result};

/// Turns one image into one global descriptor.
pub trait Extractor: Send + Sync {
    /// Descriptor length for an input image of `width x height` pixels, or an error when the
    /// extractor cannot use an image of that size.
    fn dim_for(&self, width: u32, height: u32) -> Result<usize>;

    /// The descriptor of one image. Never contains NaN or infinities.
    fn extract(&self, image: &image::DynamicImage) -> Result<Vec<f32>>;
}

/// Extracts the descriptors of `images` in parallel (rayon) into one row per image, in order.
pub fn extract_batch(
    _extractor: &dyn Extractor,
    _images: &[image::DynamicImage],
) -> Result<Matrix> {
    todo!("features helper")
}

pub mod cnn;
pub mod hog;

/// Decodes one JPEG/PNG image given as bytes; `name` (file or multipart part name) appears in
/// errors. Images with more than `max_pixels` pixels are rejected before being decoded.
pub fn decode_image(_name: &str, _bytes: &[u8], _max_pixels: u64) -> Result<image::DynamicImage> {
    todo!("features helper")
}
