//! The evaluation protocol: the ground truth in every form the field uses (a `GroundTruth`
//! class over the core's one type) and `evaluate`, the core's PR metrics plus Recall@N, as
//! `seasonloc eval` computes them.

use std::path::PathBuf;

use numpy::{PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use seasonloc_core::eval::{
    self, recall_at_n, utm_of_files, Exclusions, GroundTruth as CoreGroundTruth, Prediction,
};
use seasonloc_core::features::list_images;
use seasonloc_core::Error;

use super::{matrix, py_err};

/// Which reference images show the place of each query: one class for every form (the CSV,
/// VPR-Bench's lists, VPR_Tutorial's matrices, VPR-methods-evaluation's UTM folders).
#[pyclass(name = "GroundTruth", module = "seasonloc", frozen)]
#[derive(Clone)]
pub(crate) struct GroundTruth {
    pub(crate) inner: CoreGroundTruth,
}

#[pymethods]
impl GroundTruth {
    /// A CSV whose header has `query_index` and `ref_index` (several rows per query allowed).
    #[staticmethod]
    fn from_csv(path: PathBuf) -> PyResult<Self> {
        let inner = CoreGroundTruth::from_csv(&path).map_err(py_err)?;
        Ok(GroundTruth { inner })
    }

    /// `(query, ref)` pairs.
    #[staticmethod]
    fn from_pairs(pairs: Vec<(usize, usize)>) -> PyResult<Self> {
        let inner = CoreGroundTruth::from_pairs(pairs);
        if inner.is_empty() {
            return Err(py_err(Error::Empty("the ground truth has no pair".into())));
        }
        Ok(GroundTruth { inner })
    }

    /// VPR-Bench's rows `(query, [refs])`.
    #[staticmethod]
    fn from_query_lists(rows: Vec<(usize, Vec<usize>)>) -> PyResult<Self> {
        let inner = CoreGroundTruth::from_query_lists(&rows).map_err(py_err)?;
        Ok(GroundTruth { inner })
    }

    /// VPR_Tutorial's references x queries boolean matrix (`GThard` or `GTsoft`).
    #[staticmethod]
    fn from_match_matrix(matrix: PyReadonlyArray2<'_, bool>) -> PyResult<Self> {
        let shape = matrix.shape();
        let data: Vec<bool> = match matrix.as_slice() {
            Ok(s) => s.to_vec(),
            Err(_) => matrix.as_array().iter().copied().collect(),
        };
        let inner =
            CoreGroundTruth::from_match_matrix(shape[0], shape[1], &data).map_err(py_err)?;
        Ok(GroundTruth { inner })
    }

    /// VPR-methods-evaluation's rule on UTM positions `(east, north)` in metres.
    #[staticmethod]
    fn within_distance(
        references: Vec<(f64, f64)>,
        queries: Vec<(f64, f64)>,
        metres: f64,
    ) -> PyResult<Self> {
        let inner =
            CoreGroundTruth::within_distance(&references, &queries, metres).map_err(py_err)?;
        Ok(GroundTruth { inner })
    }

    /// VPR-methods-evaluation's folder layout: `database` and `queries` image folders (taken
    /// in file-name order) with UTM coordinates in the file names, true within `metres`.
    #[staticmethod]
    fn from_utm_folders(database: PathBuf, queries: PathBuf, metres: f64) -> PyResult<Self> {
        let refs = list_images(&database)
            .and_then(|f| utm_of_files(&f))
            .map_err(py_err)?;
        let qs = list_images(&queries)
            .and_then(|f| utm_of_files(&f))
            .map_err(py_err)?;
        let inner = CoreGroundTruth::within_distance(&refs, &qs, metres).map_err(py_err)?;
        Ok(GroundTruth { inner })
    }

    /// The true references of `query` (sorted; empty when it has none).
    fn references(&self, query: usize) -> Vec<usize> {
        self.inner.references(query).to_vec()
    }

    /// The largest query index with a true reference.
    #[getter]
    fn max_query_index(&self) -> Option<usize> {
        self.inner.max_query_index()
    }

    /// The largest reference index the ground truth names.
    #[getter]
    fn max_reference_index(&self) -> Option<usize> {
        self.inner.max_reference_index()
    }

    /// Queries with at least one true reference.
    fn __len__(&self) -> usize {
        self.inner.len()
    }

    fn __repr__(&self) -> String {
        format!(
            "GroundTruth({} queries with a true reference, largest query index {:?})",
            self.inner.len(),
            self.inner.max_query_index()
        )
    }
}

/// Query exclusions: the CLI's `--exclude` text, or inclusive `(start, end)` ranges.
#[derive(FromPyObject)]
enum Exclude {
    Text(String),
    Ranges(Vec<(usize, usize)>),
}

/// The metrics of `predictions` (`(query, ref, confidence)`) against `ground_truth`, as
/// `seasonloc eval` reports them, plus Recall@N of `similarity` (Q x D) when given.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
fn evaluate<'py>(
    py: Python<'py>,
    predictions: Vec<(usize, usize, f64)>,
    ground_truth: &GroundTruth,
    num_queries: usize,
    tolerance: usize,
    exclude: Option<Exclude>,
    similarity: Option<PyReadonlyArray2<'py, f32>>,
    ns: Vec<usize>,
) -> PyResult<Bound<'py, PyDict>> {
    let exclusions = match exclude {
        None => Exclusions::none(),
        Some(Exclude::Text(t)) => Exclusions::parse(&t).map_err(py_err)?,
        Some(Exclude::Ranges(r)) => Exclusions::from_ranges(r),
    };
    let preds: Vec<Prediction> = predictions
        .into_iter()
        .map(|(query, reference, confidence)| Prediction {
            query,
            reference,
            confidence,
            p_correct: None,
        })
        .collect();
    let s = similarity.as_ref().map(matrix).transpose()?;
    let gt = &ground_truth.inner;
    let (m, recalls) = crate::without_gil(py, || {
        let m = eval::evaluate(&preds, gt, num_queries, tolerance, &exclusions)?;
        let recalls = match &s {
            Some(s) => Some(recall_at_n(s, gt, &ns, tolerance, &exclusions)?),
            None => None,
        };
        Ok::<_, Error>((m, recalls))
    })
    .map_err(py_err)?;
    let d = PyDict::new(py);
    d.set_item("ap", m.ap)?;
    d.set_item("auc", m.auc)?;
    d.set_item("recall_at_100p", m.recall_at_100p)?;
    d.set_item("recall_at_99p", m.recall_at_99p)?;
    d.set_item("max_f1", m.max_f1)?;
    d.set_item("precision_at_full", m.precision_at_full)?;
    d.set_item("positives", m.positives)?;
    d.set_item("predicted", m.predicted)?;
    d.set_item("correct", m.correct)?;
    let curve: Vec<(f64, f64, f64)> = m
        .curve
        .iter()
        .map(|p| (p.threshold, p.precision, p.recall))
        .collect();
    d.set_item("curve", curve)?;
    if let Some(r) = recalls {
        let r: Vec<(usize, f64)> = r.iter().map(|r| (r.n, r.recall)).collect();
        d.set_item("recall_at_n", r)?;
    }
    Ok(d)
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<GroundTruth>()?;
    m.add_function(wrap_pyfunction!(evaluate, m)?)?;
    m.add("STANDARD_NS", eval::STANDARD_NS.to_vec())?;
    m.add(
        "DEFAULT_POSITIVE_DISTANCE_M",
        eval::DEFAULT_POSITIVE_DISTANCE_M,
    )?;
    Ok(())
}
