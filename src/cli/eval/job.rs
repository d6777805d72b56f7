//! One evaluation of `seasonloc eval`: the descriptor similarity matrices and/or the
//! co-occurrence map for one set of mapping drives and one query folder, every requested
//! method scored against the ground truth, the PR plot and predictions file, and the JSON
//! report (main method first, the others under `compared`).
//!
//! Why apart from the arguments: this is the work, run once for a plain evaluation and once
//! per fold by `--leave-one-out`; [`super`] only checks the arguments and picks the jobs.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::{json, Value};

use super::{ConfidenceArg, EvalArgs, Method, ReferenceDrive};
use crate::cli::plot::{plot_pr, plot_reliability};
use seasonloc_core::baselines::{best_match, seqslam, SeqSlamParams};
use seasonloc_core::calibration::fit::{expected_calibration_error, reliability, ReliabilityBin};
use seasonloc_core::confidence::ConfidenceParams;
use seasonloc_core::cooc::{CoocMethod, CoocOptions, CoocQueries};
use seasonloc_core::eval::{
    evaluate, recall_at_n, write_predictions_csv, Exclusions, GroundTruth, Metrics, Prediction,
    STANDARD_NS,
};
use seasonloc_core::features::{extract_files, image_file_size, Extractor};
use seasonloc_core::localize::{solve_with_confidence, LocalizeOptions};
use seasonloc_core::similarity::{cosine_matrix, Normalization};
use seasonloc_core::Matrix;

/// What the methods are computed from: descriptor similarity matrices and/or a co-occurrence map.
pub(super) struct Inputs<'m> {
    /// Raw cosine matrix C and its normalised ĉ (descriptor methods).
    pub(super) descriptors: Option<(Matrix, Matrix)>,
    /// The quantised queries on the co-occurrence map (co-occurrence methods).
    pub(super) cooc: Option<CoocQueries<'m>>,
}

/// One evaluation: the mapping drives, the queries and their ground truth.
pub(super) struct Job<'a> {
    pub(super) references: Vec<&'a ReferenceDrive>,
    pub(super) query: &'a Path,
    pub(super) query_files: &'a [PathBuf],
    pub(super) ground_truth: &'a GroundTruth,
}

/// Scores `methods` on one evaluation and returns its JSON report.
pub(super) fn run_job(
    args: &EvalArgs,
    methods: &[Method],
    job: &Job,
    started: Instant,
) -> Result<Value> {
    let solver = args.solver.to_params()?;
    let exclusions = Exclusions::parse(&args.exclude)?;
    let ground_truth = job.ground_truth;
    let query_files = job.query_files;
    let reference_files = &job.references[0].files;
    // Every metric is a share of the queries with a true match: with none left there is
    // nothing to measure (each would print 0).
    if !(0..query_files.len()).any(|q| !exclusions.contains(q) && ground_truth.has_match(q)) {
        bail!(
            "nothing to score: no query {}has a ground-truth match",
            if args.exclude.is_empty() {
                String::new()
            } else {
                format!("left after --exclude {} ", args.exclude)
            }
        );
    }
    let methods = methods.to_vec();
    let needs_descriptors = methods.iter().any(|m| !m.is_cooc());
    let cooc_params = methods
        .iter()
        .any(|m| m.is_cooc())
        .then(|| args.cooc.to_params())
        .transpose()?;
    let sequence = args.cooc.to_sequence()?;
    if args.save_similarity.is_some() && !needs_descriptors {
        bail!(
            "--save-similarity writes the descriptor similarity matrix C; score a descriptor \
             method (flow, best-match, seqslam) too, e.g. --compare flow"
        );
    }

    let t = Instant::now();
    let mut shapes = json!({});
    let mut inputs = Inputs {
        descriptors: None,
        cooc: None,
    };
    let mut similarity_seconds = 0.0;
    if needs_descriptors {
        // The map's input geometry is its first image's size (or --resize); every other
        // image, reference or query, is brought to it (features::geometry).
        let first_file = reference_files
            .first()
            .context("list_images returns at least one image")?;
        let first = image_file_size(first_file)?;
        let extractor = args.descriptor.to_extractor(first).with_context(|| {
            match args.descriptor.descriptor {
                // A CNN has its own input size: what fails there is the model or its settings.
                crate::cli::DescriptorKind::Cnn => "--descriptor cnn".to_string(),
                crate::cli::DescriptorKind::Hog => format!(
                    "the map's input geometry ({}x{} px, {})",
                    first.0,
                    first.1,
                    match args.descriptor.resize {
                        Some(_) => "--resize".to_string(),
                        None => format!("the first reference image {}", first_file.display()),
                    }
                ),
            }
        })?;
        let references = extract("reference", extractor.as_ref(), reference_files)?;
        let queries = extract("query", extractor.as_ref(), query_files)?;
        shapes = json!({"descriptor": args.descriptor.label(), "descriptor_dim": queries.cols()});
        if args.descriptor.descriptor == crate::cli::DescriptorKind::Hog {
            let (w, h) = args.descriptor.resize.unwrap_or(first);
            shapes["input_geometry"] = json!([w, h]);
            shapes["fit"] = json!(seasonloc_core::features::Fit::from(args.descriptor.fit).name());
        }
        let ts = Instant::now();
        let c = cosine_matrix(&queries, &references)?;
        let chat = Normalization::apply(args.normalization.into(), &c)?;
        similarity_seconds = ts.elapsed().as_secs_f64();
        if let Some(path) = &args.save_similarity {
            crate::cli::npy::write_matrix(path, &c)?;
        }
        inputs.descriptors = Some((c, chat));
    }
    let cooc_map = match &cooc_params {
        Some(params) => {
            let drives: Vec<(&[PathBuf], f64)> = job
                .references
                .iter()
                .map(|d| (d.files.as_slice(), d.time))
                .collect();
            Some(crate::cli::cooc::build_map(params, &drives, query_files)?)
        }
        None => None,
    };
    if let Some((map, query_images)) = &cooc_map {
        let queries = CoocQueries::new(map, query_images)?;
        if methods
            .iter()
            .any(|m| m.cooc().is_some_and(CoocMethod::needs_scores))
        {
            queries.scores();
            similarity_seconds += queries.score_seconds();
        }
        if !needs_descriptors {
            shapes = json!({"descriptor": "cooc", "vocabulary_words": map.vocabulary().len()});
        }
        inputs.cooc = Some(queries);
    }
    let features_seconds = t.elapsed().as_secs_f64() - similarity_seconds;

    let options = localize_options(args, solver);
    let cooc_options = CoocOptions {
        sequence,
        flow: options.clone(),
        ..CoocOptions::default()
    };
    let mut scored = Vec::new();
    for method in methods {
        let t = Instant::now();
        let (predictions, extra) = run_method(method, &inputs, &options, &cooc_options)?;
        let solve_seconds = t.elapsed().as_secs_f64();
        let metrics = evaluate(
            &predictions,
            ground_truth,
            query_files.len(),
            args.tolerance,
            &exclusions,
        )?;
        scored.push((method, predictions, metrics, extra, solve_seconds));
    }

    if let Some(path) = &args.predictions {
        write_predictions_csv(path, &scored[0].1)?;
    }
    let calibration = calibration_report(&scored[0].1, ground_truth, args.tolerance, &exclusions);
    if let Some(path) = &args.reliability {
        let Some((bins, ece)) = &calibration else {
            bail!(
                "--reliability: method `{}` gives no p_correct (only the flow methods are calibrated)",
                scored[0].0.name()
            );
        };
        plot_reliability(
            path,
            &format!("{} p_correct (ECE {ece:.3})", scored[0].0.name()),
            bins,
        )?;
    }
    if let Some(path) = &args.plot {
        let curves: Vec<(String, _)> = scored
            .iter()
            .map(|(m, _, metrics, _, _)| {
                (
                    format!("{} (AP {:.3})", m.name(), metrics.ap),
                    metrics.curve.clone(),
                )
            })
            .collect();
        let title = format!(
            "{} vs {} ({})",
            dir_name(job.query),
            job.references
                .iter()
                .map(|d| dir_name(&d.folder))
                .collect::<Vec<_>>()
                .join("+"),
            shapes["descriptor"].as_str().unwrap_or("cooc")
        );
        plot_pr(path, &title, &curves)?;
    }

    let mut reports: Vec<Value> = scored
        .iter()
        .map(|(m, _, metrics, extra, solve_seconds)| {
            method_json(*m, metrics, extra, *solve_seconds)
        })
        .collect();
    let mut report = reports.remove(0);
    let obj = report
        .as_object_mut()
        .context("method report is an object")?;
    if let Some(shapes) = shapes.as_object() {
        obj.extend(shapes.clone());
    }
    obj.insert("queries".into(), json!(query_files.len()));
    obj.insert("references".into(), json!(reference_files.len()));
    obj.insert("query".into(), json!(job.query.display().to_string()));
    obj.insert(
        "drives".into(),
        json!(job
            .references
            .iter()
            .map(|d| json!({"folder": d.folder.display().to_string(), "time": d.time}))
            .collect::<Vec<_>>()),
    );
    obj.insert(
        "normalization".into(),
        json!(format!("{:?}", args.normalization).to_lowercase()),
    );
    obj.insert("tolerance".into(), json!(args.tolerance));
    obj.insert("exclude".into(), json!(args.exclude));
    let solve_seconds = obj
        .get("seconds")
        .and_then(|s| s.get("solve"))
        .cloned()
        .unwrap_or(json!(0.0));
    obj.insert(
        "seconds".into(),
        json!({
            "features": features_seconds,
            "similarity": similarity_seconds,
            "solve": solve_seconds,
            "total": started.elapsed().as_secs_f64(),
        }),
    );
    obj.insert("compared".into(), Value::Array(reports));
    if let Some((c, _)) = &inputs.descriptors {
        // The field's retrieval metric, of the descriptors: the ranking of the raw cosine C.
        let recalls = recall_at_n(c, ground_truth, &STANDARD_NS, args.tolerance, &exclusions)?;
        let recalls: serde_json::Map<String, Value> = recalls
            .iter()
            .map(|r| (r.n.to_string(), json!(r.recall)))
            .collect();
        obj.insert("recall_at_n".into(), Value::Object(recalls));
    }
    if let Some((bins, ece)) = &calibration {
        let by_p: Vec<Prediction> = scored[0]
            .1
            .iter()
            .map(|p| Prediction {
                confidence: p.p_correct.unwrap_or(0.0),
                ..*p
            })
            .collect();
        let metrics = evaluate(
            &by_p,
            ground_truth,
            query_files.len(),
            args.tolerance,
            &exclusions,
        )?;
        obj.insert("calibration".into(), calibration_json(bins, *ece, &metrics));
    }
    Ok(report)
}

/// The flow method's options from the flags (claim: `--claim`, else the tolerance).
pub(super) fn localize_options(
    args: &EvalArgs,
    solver: seasonloc_core::solver::SolverParams,
) -> LocalizeOptions {
    LocalizeOptions {
        solver,
        normalization: args.normalization.into(),
        confidence: ConfidenceParams {
            radius: args.confidence_radius,
            discount: match args.confidence {
                ConfidenceArg::Discounted => Some(args.confidence_discount),
                ConfidenceArg::Window => None,
            },
            ..ConfidenceParams::default()
        },
        claim: args.claim.unwrap_or(args.tolerance),
        tolerance: args.tolerance,
    }
}

pub(super) fn run_method(
    method: Method,
    inputs: &Inputs,
    options: &LocalizeOptions,
    cooc_options: &CoocOptions,
) -> Result<(Vec<Prediction>, Value)> {
    let flow_params = |solution: &seasonloc_core::solver::Solution| {
        json!({
            "hidden_cost": solution.hidden_cost,
            "fan_out": options.solver.fan_out,
            "flows": options.solver.flows,
            "exact": options.solver.exact,
            "horizontal": options.solver.horizontal,
            "hypotheses": solution.hypotheses.len(),
            "total_cost": solution.total_cost(),
        })
    };
    if let Some(cooc) = method.cooc() {
        let queries = inputs
            .cooc
            .as_ref()
            .context("the co-occurrence map is built for every cooc method")?;
        let result = queries.localize(cooc, cooc_options)?;
        let mut extra = match cooc {
            CoocMethod::Single => json!({"schedule": "best-first"}),
            CoocMethod::Sequence => {
                let s = &cooc_options.sequence;
                json!({"length": s.length, "max_step": s.max_step, "exclusion": s.exclusion,
                       "contrast_window": s.contrast_window,
                       "normalization": format!("{:?}", s.normalization)})
            }
            CoocMethod::Flow => flow_params(&result.solution),
        };
        if let Some(obj) = extra.as_object_mut() {
            obj.insert("words".into(), json!(queries.map().vocabulary().len()));
        }
        return Ok((result.predictions, extra));
    }
    let (c, chat) = inputs
        .descriptors
        .as_ref()
        .context("descriptors are extracted for every descriptor method")?;
    Ok(match method {
        Method::BestMatch => (best_match(c), json!({})),
        Method::Seqslam => {
            let params = SeqSlamParams::default();
            (seqslam(c, &params)?, json!({}))
        }
        _ => {
            let (solution, predictions) = solve_with_confidence(chat, options)?;
            (predictions, flow_params(&solution))
        }
    })
}

/// Bins of the reliability diagram and of the expected calibration error.
const CALIBRATION_BINS: usize = 10;

/// The reliability of `predictions`' `p_correct` against the ground truth (scored queries only;
/// a prediction for a query without a true match is wrong): the diagram's bins and the expected
/// calibration error. `None` when the method gives no `p_correct`.
fn calibration_report(
    predictions: &[Prediction],
    ground_truth: &GroundTruth,
    tolerance: usize,
    exclusions: &Exclusions,
) -> Option<(Vec<ReliabilityBin>, f64)> {
    let pairs: Vec<(f64, bool)> = predictions
        .iter()
        .filter(|p| !exclusions.contains(p.query))
        .map(|p| {
            p.p_correct
                .map(|pc| (pc, ground_truth.is_correct(p.query, p.reference, tolerance)))
        })
        .collect::<Option<_>>()?;
    Some((
        reliability(&pairs, CALIBRATION_BINS),
        expected_calibration_error(&pairs, CALIBRATION_BINS),
    ))
}

/// The report's `calibration` entry: ECE, the bins, and the metrics of the predictions ranked
/// by `p_correct` instead of the method's confidence.
fn calibration_json(bins: &[ReliabilityBin], ece: f64, by_p: &Metrics) -> Value {
    json!({
        "ece": ece,
        "bins": bins
            .iter()
            .map(|b| json!({"lo": b.lo, "hi": b.hi, "count": b.count, "predicted": b.predicted, "observed": b.observed}))
            .collect::<Vec<_>>(),
        "ranked_by_p_correct": {
            "ap": by_p.ap,
            "recall_at_100p": by_p.recall_at_100p,
            "recall_at_99p": by_p.recall_at_99p,
            "max_f1": by_p.max_f1,
        },
    })
}

/// The figures of `m` as `eval` prints them (also `drive --ground-truth`'s).
pub fn metrics_json(m: &Metrics) -> Value {
    json!({
        "ap": m.ap,
        "recall_at_100p": m.recall_at_100p,
        "recall_at_99p": m.recall_at_99p,
        "max_f1": m.max_f1,
        "precision_at_full": m.precision_at_full,
        "auc": m.auc,
        "predicted": m.predicted,
        "correct": m.correct,
        "positives": m.positives,
    })
}

pub(super) fn method_json(method: Method, m: &Metrics, extra: &Value, solve_seconds: f64) -> Value {
    let mut v = json!({"method": method.name()});
    if let (Some(obj), Value::Object(figures)) = (v.as_object_mut(), metrics_json(m)) {
        obj.extend(figures);
        obj.insert("seconds".into(), json!({"solve": solve_seconds}));
    }
    if let (Some(obj), Some(extra)) = (v.as_object_mut(), extra.as_object()) {
        if !extra.is_empty() {
            obj.insert("params".into(), Value::Object(extra.clone()));
        }
    }
    v
}

fn extract(what: &str, extractor: &dyn Extractor, files: &[PathBuf]) -> Result<Matrix> {
    let bar = ProgressBar::new(files.len() as u64).with_message(format!("{what} features"));
    bar.set_style(
        ProgressStyle::with_template("{msg:>18} [{bar:30}] {pos}/{len} {elapsed}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let result = extract_files(extractor, files, &|| bar.inc(1));
    bar.finish_and_clear();
    Ok(result?)
}

fn dir_name(path: &Path) -> String {
    path.file_name().map_or_else(
        || path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    )
}
