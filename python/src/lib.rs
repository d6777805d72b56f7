//! `seasonloc._native`: the Python package's extension module, a thin PyO3 binding over
//! `seasonloc-core`. No algorithm lives here: every function converts its arguments, calls the
//! same core function the CLI calls, and converts the answer back. The public, documented API
//! (argument forms, result classes) is the Python code in `python/seasonloc/`.
//!
//! Every call that computes releases the GIL (`Python::allow_threads`) after copying its
//! arrays into core matrices, and runs on its Python thread's own rayon pool
//! (`without_gil`), so Python threads solve in parallel. A core error becomes a
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

thread_local! {
    /// This Python thread's rayon pool, made at its first call (`None` if it could not be).
    static POOL: std::cell::OnceCell<Option<rayon::ThreadPool>> = const { std::cell::OnceCell::new() };
}

/// Runs `work` without the GIL, on the calling Python thread's own rayon pool of
/// `rayon::current_num_threads()` threads (`RAYON_NUM_THREADS`, else one per core). On the
/// one global pool, calls from several Python threads would queue for the same workers (with
/// `RAYON_NUM_THREADS=1`, run one after the other); each thread's pool lets them run at once,
/// as separate processes would.
pub(crate) fn without_gil<T: Send>(py: Python<'_>, work: impl FnOnce() -> T + Send) -> T {
    py.allow_threads(|| {
        POOL.with(|pool| {
            let pool = pool.get_or_init(|| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(rayon::current_num_threads())
                    .build()
                    .ok()
            });
            match pool {
                Some(p) => p.install(work),
                None => work(),
            }
        })
    })
}

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
