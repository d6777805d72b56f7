//! `seasonloc eval --leave-one-out`: the co-occurrence paper's protocol over the
//! `--reference` traversals of one route. Each in turn is the query and the others form the
//! map (one [`super::job`] per fold); the report holds every fold and the mean of each metric
//! over the folds, for the main method and every compared one.
//!
//! Why apart: a second protocol over the same job, with its own checks (co-occurrence methods
//! only, at least two traversals) and its own report shape.

use std::time::Instant;

use anyhow::{bail, Result};
use serde_json::{json, Value};

use super::job::{run_job, Job};
use super::{check_ground_truth, EvalArgs, ReferenceDrive};
use seasonloc_core::eval::GroundTruth;

/// Metric fields averaged over the folds of `--leave-one-out`.
const METRIC_FIELDS: [&str; 5] = [
    "ap",
    "recall_at_100p",
    "recall_at_99p",
    "max_f1",
    "precision_at_full",
];

/// The paper's protocol: each `--reference` folder in turn is the query, the others the map.
pub(super) fn leave_one_out(
    args: &EvalArgs,
    drives: &[ReferenceDrive],
    started: Instant,
) -> Result<Value> {
    let mut methods = vec![args.method];
    methods.extend(args.compare.iter().copied().filter(|m| *m != args.method));
    if let Some(m) = methods.iter().find(|m| !m.is_cooc()) {
        bail!(
            "--leave-one-out fuses the other traversals into one map: only the co-occurrence \
             methods (cooc, cooc-seq, cooc-flow) can, not `{}`",
            m.name()
        );
    }
    if drives.len() < 2 {
        bail!("--leave-one-out needs at least two --reference traversals of the route");
    }
    if args.predictions.is_some() || args.plot.is_some() {
        bail!("--predictions and --plot describe one evaluation; not with --leave-one-out");
    }
    let locations = drives[0].files.len();
    let ground_truth = match &args.ground_truth {
        Some(path) => {
            let gt = crate::cli::ground_truth::load(path, args.soft_ground_truth)?;
            let drive = (drives[0].folder.as_path(), locations);
            check_ground_truth(&gt, path, drive, drive)?;
            gt
        }
        None => GroundTruth::from_pairs((0..locations).map(|k| (k, k))),
    };
    let mut folds = Vec::with_capacity(drives.len());
    for (q, query) in drives.iter().enumerate() {
        let job = Job {
            references: drives
                .iter()
                .enumerate()
                .filter(|&(k, _)| k != q)
                .map(|(_, d)| d)
                .collect(),
            query: &query.folder,
            query_files: &query.files,
            ground_truth: &ground_truth,
        };
        folds.push(run_job(args, &methods, &job, Instant::now())?);
    }
    let mut report = json!({
        "protocol": "leave-one-out",
        "method": args.method.name(),
        "descriptor": "cooc",
        "queries": locations * drives.len(),
        "references": locations,
        "tolerance": args.tolerance,
        "exclude": args.exclude,
    });
    let mut compared = Vec::new();
    for (i, m) in methods.iter().enumerate().skip(1) {
        let mut c = json!({"method": m.name()});
        for field in METRIC_FIELDS {
            c[field] = json!(fold_mean(&folds, Some(i - 1), field));
        }
        compared.push(c);
    }
    for field in METRIC_FIELDS {
        report[field] = json!(fold_mean(&folds, None, field));
    }
    let sum_seconds = |stage: &str| -> f64 {
        folds
            .iter()
            .filter_map(|f| f["seconds"][stage].as_f64())
            .sum()
    };
    report["seconds"] = json!({
        "features": sum_seconds("features"),
        "similarity": sum_seconds("similarity"),
        "solve": sum_seconds("solve"),
        "total": started.elapsed().as_secs_f64(),
    });
    report["compared"] = Value::Array(compared);
    report["folds"] = Value::Array(folds);
    Ok(report)
}

/// The mean of `field` over the folds' reports: of the main method (`compared = None`) or of
/// the `compared[k]` method.
fn fold_mean(folds: &[Value], compared: Option<usize>, field: &str) -> f64 {
    let sum: f64 = folds
        .iter()
        .filter_map(|f| {
            let report = match compared {
                Some(k) => f.get("compared")?.get(k)?,
                None => f,
            };
            report.get(field)?.as_f64()
        })
        .sum();
    sum / folds.len().max(1) as f64
}
