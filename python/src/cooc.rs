//! The co-occurrence method (Johns & Yang's feature co-occurrence maps) on images: a map
//! built from one mapping drive, the queries localized by one of its three methods, as
//! `seasonloc eval --method cooc|cooc-seq|cooc-flow` does with its default parameters.

use std::path::PathBuf;

use image::GrayImage;
use numpy::PyReadonlyArrayDyn;
use pyo3::prelude::*;
use rayon::prelude::*;

use seasonloc_core::cooc::{localize, CoocMap, CoocMethod, CoocOptions, CoocParams, Drive};
use seasonloc_core::features::{load_image_file_as, to_gray, Pixels};
use seasonloc_core::localize::LocalizeOptions;
use seasonloc_core::Error;

use super::describe::images;
use super::methods::{prediction_rows, PredictionRow};
use super::py_err;

/// Gray images from paths (loaded as the CLI loads them) or decoded arrays.
fn gray(
    paths: Option<Vec<PathBuf>>,
    arrays: Option<Vec<PyReadonlyArrayDyn<'_, u8>>>,
) -> PyResult<Vec<GrayImage>> {
    match (paths, arrays) {
        (Some(p), None) => p
            .par_iter()
            .map(|f| Ok(load_image_file_as(f, Pixels::Gray)?.into_luma8()))
            .collect::<seasonloc_core::Result<_>>()
            .map_err(py_err),
        (None, Some(a)) => Ok(images(&a)?
            .iter()
            .map(|i| to_gray(i).into_owned())
            .collect()),
        _ => Err(py_err(Error::param(
            "images",
            "give image paths or decoded images",
        ))),
    }
}

/// `method` (`cooc`, `cooc-seq`, `cooc-flow`) on a map of the reference images.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
fn cooc(
    py: Python<'_>,
    reference_paths: Option<Vec<PathBuf>>,
    reference_arrays: Option<Vec<PyReadonlyArrayDyn<'_, u8>>>,
    query_paths: Option<Vec<PathBuf>>,
    query_arrays: Option<Vec<PyReadonlyArrayDyn<'_, u8>>>,
    method: &str,
    tolerance: usize,
) -> PyResult<Vec<PredictionRow>> {
    let method: CoocMethod = method.parse().map_err(|e: Error| py_err(e))?;
    let refs = gray(reference_paths, reference_arrays)?;
    let queries = gray(query_paths, query_arrays)?;
    crate::without_gil(py, || {
        let map = CoocMap::build(&CoocParams::default(), &[Drive::sequential(0.0, refs)?])?;
        let options = CoocOptions {
            flow: LocalizeOptions {
                claim: tolerance,
                tolerance,
                ..LocalizeOptions::default()
            },
            ..CoocOptions::default()
        };
        Ok(prediction_rows(
            &localize(&map, &queries, method, &options)?.predictions,
        ))
    })
    .map_err(py_err)
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(cooc, m)?)
}
