//! The descriptors: HOG and a CNN layer, from image files or from decoded pixel arrays, by the
//! core extractors `seasonloc eval` uses (`Fitted::hog`, `CnnSpec`), across cores without the
//! GIL.

use std::path::PathBuf;

use image::{DynamicImage, GrayImage, RgbImage, RgbaImage};
use numpy::{PyArray2, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;

use seasonloc_core::features::{
    extract_batch, extract_files, image_file_size, Extractor, Fit, Fitted,
};
use seasonloc_core::{Error, Matrix};

use super::{array, py_err};

/// Decoded images as the package passes them: `H x W` (gray), `H x W x 3` (RGB) or
/// `H x W x 4` (RGBA) uint8 arrays.
pub(crate) fn images(arrays: &[PyReadonlyArrayDyn<'_, u8>]) -> PyResult<Vec<DynamicImage>> {
    arrays
        .iter()
        .enumerate()
        .map(|(i, a)| {
            let shape = a.shape().to_vec();
            let data: Vec<u8> = match a.as_slice() {
                Ok(s) => s.to_vec(),
                Err(_) => a.as_array().iter().copied().collect(),
            };
            let bad = || {
                py_err(Error::Image {
                    name: format!("image #{i}"),
                    reason: format!(
                        "expected an H x W, H x W x 3 or H x W x 4 uint8 array, got shape {shape:?}"
                    ),
                })
            };
            let (h, w, c) = match shape[..] {
                [h, w] => (h, w, 1),
                [h, w, c] if matches!(c, 1 | 3 | 4) => (h, w, c),
                _ => return Err(bad()),
            };
            let (w, h) = (
                u32::try_from(w).map_err(|_| bad())?,
                u32::try_from(h).map_err(|_| bad())?,
            );
            let img = match c {
                1 => GrayImage::from_raw(w, h, data).map(DynamicImage::ImageLuma8),
                3 => RgbImage::from_raw(w, h, data).map(DynamicImage::ImageRgb8),
                _ => RgbaImage::from_raw(w, h, data).map(DynamicImage::ImageRgba8),
            };
            img.ok_or_else(bad)
        })
        .collect()
}

fn fit(name: &str) -> PyResult<Fit> {
    match name {
        "stretch" => Ok(Fit::Stretch),
        "crop" => Ok(Fit::Crop),
        other => Err(py_err(Error::param(
            "fit",
            format!("expected `stretch` or `crop`, got `{other}`"),
        ))),
    }
}

/// One descriptor row per image file, in order.
fn from_files(py: Python<'_>, extractor: &dyn Extractor, paths: &[PathBuf]) -> PyResult<Matrix> {
    crate::without_gil(py, || extract_files(extractor, paths, &|| {})).map_err(py_err)
}

/// HOG descriptors of image files (one row per file, in order). The input geometry is
/// `resize` or the first image's size, as the CLI's map geometry.
#[pyfunction]
fn hog_files<'py>(
    py: Python<'py>,
    paths: Vec<PathBuf>,
    cell_size: u32,
    resize: Option<(u32, u32)>,
    fit_name: &str,
) -> PyResult<Bound<'py, PyArray2<f32>>> {
    let first = paths.first().ok_or_else(|| {
        py_err(Error::Empty(
            "no image files to extract descriptors from".into(),
        ))
    })?;
    let geometry = match resize {
        Some(g) => g,
        None => image_file_size(first).map_err(py_err)?,
    };
    let extractor = Fitted::hog(cell_size, geometry, fit(fit_name)?).map_err(py_err)?;
    let m = from_files(py, &extractor, &paths)?;
    array(py, m)
}

/// HOG descriptors of decoded images (uint8 arrays).
#[pyfunction]
fn hog_arrays<'py>(
    py: Python<'py>,
    arrays: Vec<PyReadonlyArrayDyn<'py, u8>>,
    cell_size: u32,
    resize: Option<(u32, u32)>,
    fit_name: &str,
) -> PyResult<Bound<'py, PyArray2<f32>>> {
    let imgs = images(&arrays)?;
    let first = imgs
        .first()
        .ok_or_else(|| py_err(Error::Empty("no images to extract descriptors from".into())))?;
    let geometry = resize.unwrap_or((first.width(), first.height()));
    let extractor = Fitted::hog(cell_size, geometry, fit(fit_name)?).map_err(py_err)?;
    let m = crate::without_gil(py, || extract_batch(&extractor, &imgs)).map_err(py_err)?;
    array(py, m)
}

#[cfg(feature = "cnn")]
mod cnn {
    use super::*;
    use seasonloc_core::features::cnn::{CnnOptions, CnnResize, CnnSpec};

    /// The CNN settings (the CLI's `--cnn-*` flags and their defaults).
    #[allow(clippy::too_many_arguments)]
    fn spec(
        model: PathBuf,
        layer: String,
        input_size: (u32, u32),
        crop: bool,
        short_side: Option<u32>,
        mean: [f32; 3],
        scale: [f32; 3],
    ) -> PyResult<CnnSpec> {
        let (w, h) = input_size;
        let resize = if crop {
            CnnResize::ShortSideCrop {
                short_side: short_side.unwrap_or_else(|| (w.max(h) * 256).div_ceil(224)),
            }
        } else {
            CnnResize::Stretch
        };
        CnnSpec::new(CnnOptions {
            model,
            layer,
            input_size,
            resize,
            mean,
            scale,
        })
        .map_err(py_err)
    }

    /// CNN descriptors of image files or decoded images (exactly one of `paths`, `arrays`).
    #[pyfunction]
    #[allow(clippy::too_many_arguments)]
    pub(super) fn cnn<'py>(
        py: Python<'py>,
        paths: Option<Vec<PathBuf>>,
        arrays: Option<Vec<PyReadonlyArrayDyn<'py, u8>>>,
        model: PathBuf,
        layer: String,
        input_size: (u32, u32),
        crop: bool,
        short_side: Option<u32>,
        mean: [f32; 3],
        scale: [f32; 3],
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let extractor = spec(model, layer, input_size, crop, short_side, mean, scale)?;
        let m = match (paths, arrays) {
            (Some(paths), None) => from_files(py, &extractor, &paths)?,
            (None, Some(arrays)) => {
                let imgs = images(&arrays)?;
                crate::without_gil(py, || extract_batch(&extractor, &imgs)).map_err(py_err)?
            }
            _ => {
                return Err(py_err(Error::param(
                    "images",
                    "give image paths or decoded images",
                )))
            }
        };
        array(py, m)
    }
}

/// The images of a folder in file-name order, as `seasonloc eval` takes them.
#[pyfunction]
fn list_images(folder: PathBuf) -> PyResult<Vec<PathBuf>> {
    seasonloc_core::features::list_images(&folder).map_err(py_err)
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(list_images, m)?)?;
    m.add_function(wrap_pyfunction!(hog_files, m)?)?;
    m.add_function(wrap_pyfunction!(hog_arrays, m)?)?;
    #[cfg(feature = "cnn")]
    m.add_function(wrap_pyfunction!(cnn::cnn, m)?)?;
    m.add("HAS_CNN", cfg!(feature = "cnn"))?;
    Ok(())
}
