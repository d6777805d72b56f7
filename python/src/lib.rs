//! `seasonloc._native`: the Python package's extension module, a thin PyO3 binding over
//! `seasonloc-core`. No algorithm lives here: every function converts its arguments, calls the
//! same core function the CLI calls, and converts the answer back. The public, documented API
//! (argument forms, result classes) is the Python code in `python/seasonloc/`.
//!
//! Every call that computes releases the GIL (`Python::allow_threads`) after copying its
//! arrays into core matrices, so Python threads solve in parallel. A core error becomes a
//! `ValueError` (an I/O error an `OSError`) carrying the message the CLI prints.

use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::{PyOSError, PyValueError};
use pyo3::prelude::*;

use seasonloc_core::{Error, Matrix};

mod cooc;
mod describe;
mod evaluate;
mod methods;
mod trip;

/// A core error as the Python exception the package raises, with the CLI's message.
fn py_err(e: Error) -> PyErr {
    match e {
        Error::Io { .. } => PyOSError::new_err(e.to_string()),
        _ => PyValueError::new_err(e.to_string()),
    }
}

/// A 2-D float32 array (C-contiguous or not) copied into a core [`Matrix`].
fn matrix(a: &PyReadonlyArray2<'_, f32>) -> PyResult<Matrix> {
    let shape = a.shape();
    let (rows, cols) = (shape[0], shape[1]);
    let data = match a.as_slice() {
        Ok(s) => s.to_vec(),
        Err(_) => a.as_array().iter().copied().collect(),
    };
    Matrix::from_vec(rows, cols, data).map_err(py_err)
}

/// A core [`Matrix`] as a new 2-D float32 NumPy array.
fn array(py: Python<'_>, m: Matrix) -> PyResult<Bound<'_, PyArray2<f32>>> {
    let (rows, cols) = (m.rows(), m.cols());
    let a = Array2::from_shape_vec((rows, cols), m.into_vec())
        .map_err(|e| PyValueError::new_err(format!("internal shape error: {e}")))?;
    Ok(a.into_pyarray(py))
}

/// The extension module.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    methods::register(m)?;
    describe::register(m)?;
    cooc::register(m)?;
    evaluate::register(m)?;
    trip::register(m)?;
    Ok(())
}
