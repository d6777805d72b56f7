//! The online trip: a vehicle's frames (as descriptors) pushed in batches against a map's
//! reference descriptors, each batch answered with per-frame estimates, by the core `Trip` the
//! service runs for `POST /v1/trips/{id}/frames`.

use std::sync::Mutex;

use numpy::PyReadonlyArray2;
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;

use seasonloc_core::similarity::{cosine_matrix_normalized, l2_normalized_rows};
use seasonloc_core::trip::{column_prior, Trip as CoreTrip, TripParams, TripStatus};
use seasonloc_core::Matrix;

use super::{matrix, py_err};

/// `(frame, ref or None, confidence, p_correct, status)` per frame.
type EstimateRow = (usize, Option<usize>, f64, f64, &'static str);

/// A trip on one map: `push` a batch of query descriptors, get their estimates.
#[pyclass(name = "_Trip", module = "seasonloc")]
pub(crate) struct Trip {
    /// The map's references, L2-normalised once (as the service caches them).
    references: Matrix,
    /// The trip's state; a lock so that a push runs without the GIL.
    state: Mutex<CoreTrip>,
}

#[pymethods]
impl Trip {
    #[new]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        references: PyReadonlyArray2<'_, f32>,
        fan_out: usize,
        hidden_cost: Option<f64>,
        horizontal: bool,
        lag: usize,
        relocalization: Option<f64>,
        normalize: bool,
        tolerance: usize,
        threshold: f64,
    ) -> PyResult<Self> {
        let refs = matrix(&references)?;
        let params = TripParams {
            fan_out,
            hidden_cost,
            horizontal,
            lag,
            relocalization,
            normalize,
            tolerance,
            threshold,
            ..TripParams::default()
        };
        params.validate().map_err(py_err)?;
        let (references, trip) = crate::without_gil(py, || {
            refs.check_finite("reference descriptors")?;
            let prior = column_prior(&refs)?;
            Ok((l2_normalized_rows(&refs), CoreTrip::new(prior, params)?))
        })
        .map_err(py_err)?;
        Ok(Trip {
            references,
            state: Mutex::new(trip),
        })
    }

    /// Pushes a batch of query descriptors (one row per frame, in driving order); returns the
    /// new frames' estimates and the trip's status.
    fn push(
        &self,
        py: Python<'_>,
        descriptors: PyReadonlyArray2<'_, f32>,
    ) -> PyResult<(Vec<EstimateRow>, &'static str)> {
        let batch = matrix(&descriptors)?;
        let update = crate::without_gil(py, || {
            let mut trip = self
                .state
                .lock()
                .map_err(|_| PyRuntimeError::new_err("the trip failed in an earlier push"))?;
            let c = cosine_matrix_normalized(&batch, &self.references).map_err(py_err)?;
            trip.push_batch(&c).map_err(py_err)
        })?;
        let rows = update
            .estimates
            .iter()
            .map(|e| {
                (
                    e.frame,
                    e.reference,
                    e.confidence,
                    e.p_correct,
                    e.status.as_str(),
                )
            })
            .collect();
        let status = match update.status {
            TripStatus::Localized => "localized",
            TripStatus::Lost => "lost",
            TripStatus::Relocalized => "relocalized",
        };
        Ok((rows, status))
    }

    /// Frames pushed so far.
    #[getter]
    fn frames(&self) -> PyResult<usize> {
        let trip = self
            .state
            .lock()
            .map_err(|_| PyRuntimeError::new_err("the trip failed in an earlier push"))?;
        Ok(trip.frames())
    }
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Trip>()
}
