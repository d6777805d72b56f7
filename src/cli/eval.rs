//! `seasonloc eval`: descriptors for two image folders, one or more localization methods, and
//! the metrics of spec §4, printed as one JSON object on stdout.
//!
//! All inputs are validated before the expensive work starts (folders, ground truth, ranges,
//! output locations), so a typo fails in milliseconds. Methods:
//! * `flow` — the flow paper's graph on the column-normalised matrix ĉ; confidence = the local
//!   min-marginal ratio (`confidence` module);
//! * `best-match` — per query the reference with the highest cosine similarity C; confidence = C;
//! * `seqslam` — SeqSLAM on the difference matrix 1 - C; confidence = its uniqueness ratio;
//! * `cooc` — co-occurrence map single-image recognition; confidence = consistent-group size;
//! * `cooc-seq` — the co-occurrence paper's sequence matching; confidence = its margin;
//! * `cooc-flow` — the co-occurrence scores (`s + 1`, then `--normalization`) as the flow
//!   graph's similarity matrix; confidence as for `flow`.
//!
//! The co-occurrence methods use the images (see [`super::cooc`]), not `--descriptor`; the
//! descriptor (and a CNN model) is only loaded when a descriptor method is scored.
//!
//! **Several mapping drives** (co-occurrence methods only): `--reference` may be repeated, one
//! folder per drive of the same route; image `k` of every drive is location `k` (so every drive
//! must hold the same number of images; the error names the drive that differs), and the ground
//! truth's `ref_index` is a location. `--reference-time` (once per drive) gives each drive's
//! time of day for the interpolation between drives adjacent in time (paper II-E); by default
//! the drives are in the order given. `--leave-one-out` runs the paper's protocol over the
//! `--reference` folders (all traversals of the route): each in turn is the query, the others
//! form the map; the report holds every fold and the mean of each metric over the folds.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::{json, Value};

use super::cooc::CoocArgs;
use super::{DescriptorArgs, SolverArgs};
use crate::baselines::{best_match, seqslam, SeqSlamParams};
use crate::confidence::ConfidenceParams;
use crate::cooc::{CoocMethod, CoocOptions, CoocQueries};
use crate::eval::{
    evaluate, plot_pr, write_predictions_csv, Exclusions, GroundTruth, Metrics, Prediction,
};
use crate::features::{extract_files, image_file_size, list_images, Extractor};
use crate::localize::{solve_with_confidence, LocalizeOptions};
use crate::similarity::{cosine_matrix, Normalization};
use crate::Error;
use crate::Matrix;

/// Localization methods `eval` can score.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Method {
    /// Network flow on the data-association graph (flow paper).
    Flow,
    /// Single-image best match.
    BestMatch,
    /// SeqSLAM (Milford & Wyeth 2012, as in OpenSeqSLAM).
    Seqslam,
    /// Co-occurrence map, single-image recognition (Johns & Yang 2013).
    Cooc,
    /// Co-occurrence map with the paper's sequence matching.
    CoocSeq,
    /// Co-occurrence scores as the network-flow graph's similarity matrix.
    CoocFlow,
}

impl Method {
    fn name(self) -> &'static str {
        match self {
            Method::Flow => "flow",
            Method::BestMatch => "best-match",
            Method::Seqslam => "seqslam",
            Method::Cooc => "cooc",
            Method::CoocSeq => "cooc-seq",
            Method::CoocFlow => "cooc-flow",
        }
    }

    /// The co-occurrence method this is, if it is one.
    fn cooc(self) -> Option<CoocMethod> {
        match self {
            Method::Cooc => Some(CoocMethod::Single),
            Method::CoocSeq => Some(CoocMethod::Sequence),
            Method::CoocFlow => Some(CoocMethod::Flow),
            Method::Flow | Method::BestMatch | Method::Seqslam => None,
        }
    }

    fn is_cooc(self) -> bool {
        self.cooc().is_some()
    }
}

/// `--confidence` values (flow method).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ConfidenceArg {
    /// The discounted min-marginal ratio (default; `O(Q·D)` in total).
    Discounted,
    /// The local min-marginal ratio on the 11-row box window (the trips' confidence).
    Window,
}

/// `--normalization` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum NormalizationArg {
    /// Eq. 2 with the column mean floored at half the median column mean (default).
    Floored,
    /// The paper's Eq. 2 exactly.
    Eq2,
    /// Raw cosine similarities.
    None,
}

impl From<NormalizationArg> for Normalization {
    fn from(n: NormalizationArg) -> Self {
        match n {
            NormalizationArg::Floored => Normalization::FlooredColumns,
            NormalizationArg::Eq2 => Normalization::Columns,
            NormalizationArg::None => Normalization::None,
        }
    }
}

/// Flags of `seasonloc eval`.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Folder of reference (map) images, taken in file-name order. The co-occurrence methods
    /// fuse several mapping drives of one route: repeat the flag (image k of every drive =
    /// location k).
    #[arg(long, required = true)]
    pub reference: Vec<PathBuf>,
    /// Time of day of each `--reference` drive (repeat once per drive, same order; any number
    /// whose order is the drives' order in time, e.g. hours), for the co-occurrence map's
    /// interpolation between drives adjacent in time. Default: the order given.
    #[arg(long, allow_negative_numbers = true)]
    pub reference_time: Vec<f64>,
    /// Folder of query images, taken in file-name order.
    #[arg(long)]
    pub query: Option<PathBuf>,
    /// Ground-truth CSV with a header holding at least `query_index,ref_index`. Optional with
    /// `--leave-one-out`, where it defaults to query k -> location k.
    #[arg(long)]
    pub ground_truth: Option<PathBuf>,
    /// The co-occurrence paper's protocol over the `--reference` folders (all traversals of one
    /// route, at least two): each traversal in turn is the query, the others form the map.
    #[arg(long, conflicts_with = "query")]
    pub leave_one_out: bool,
    /// Method to score.
    #[arg(long, value_enum, default_value_t = Method::Flow)]
    pub method: Method,
    /// Further methods scored on the same descriptors (comma-separated), reported under
    /// `compared` and drawn on the same plot.
    #[arg(long, value_enum, value_delimiter = ',')]
    pub compare: Vec<Method>,
    /// A prediction is correct within this many reference frames of a true match.
    #[arg(long, default_value_t = 0)]
    pub tolerance: usize,
    /// Query index ranges left out of scoring, e.g. `0-16,100-120`.
    #[arg(long, default_value = "")]
    pub exclude: String,
    /// Write `query_index,ref_index,confidence` of the main method here.
    #[arg(long)]
    pub predictions: Option<PathBuf>,
    /// Write a precision-recall plot (PNG) of all scored methods here.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Write the raw cosine similarity matrix C (Q x D, float32 .npy) here, e.g. to feed
    /// `seasonloc solve --normalize`.
    #[arg(long)]
    pub save_similarity: Option<PathBuf>,
    /// Normalisation of C before the graph: `floored` (Eq. 2 with the column mean floored at
    /// half the median column mean), `eq2` (the paper's Eq. 2 exactly) or `none`.
    #[arg(long, value_enum, default_value_t = NormalizationArg::Floored)]
    pub normalization: NormalizationArg,
    /// Flow confidence: alternatives within this many reference frames of a prediction
    /// count as the same place (`r`).
    #[arg(long, default_value_t = 2)]
    pub confidence_radius: usize,
    /// Flow confidence: `discounted` (the min-marginal ratio with rows weighted `G^|t-i|`,
    /// `O(Q·D)` in total) or `window` (the 11-row box window of earlier versions, the trips'
    /// confidence; `12·D` work per matched row).
    #[arg(long, value_enum, default_value_t = ConfidenceArg::Discounted)]
    pub confidence: ConfidenceArg,
    /// Flow confidence `discounted`: the weight `G` of a row one frame further away, 0 < G < 1.
    #[arg(long, default_value_t = crate::confidence::DEFAULT_DISCOUNT)]
    pub confidence_discount: f64,
    /// Flow, `discounted`: frames a prediction claims on each side of the frame it names. The
    /// frame named is the one within that many frames of the path's match whose neighbourhood
    /// the evidence supports best (0: the path's match). Default: `--tolerance`, the precision
    /// the predictions are scored at.
    #[arg(long)]
    pub claim: Option<usize>,
    /// Descriptor settings.
    #[command(flatten)]
    pub descriptor: DescriptorArgs,
    /// Graph and solver parameters (flow method).
    #[command(flatten)]
    pub solver: SolverArgs,
    /// Co-occurrence parameters (`cooc`, `cooc-seq`, `cooc-flow`).
    #[command(flatten)]
    pub cooc: CoocArgs,
}

/// What the methods are computed from: descriptor similarity matrices and/or a co-occurrence map.
struct Inputs<'m> {
    /// Raw cosine matrix C and its normalised ĉ (descriptor methods).
    descriptors: Option<(Matrix, Matrix)>,
    /// The quantised queries on the co-occurrence map (co-occurrence methods).
    cooc: Option<CoocQueries<'m>>,
}

/// One mapping drive: its folder, its images in file-name order and its time key.
struct ReferenceDrive {
    folder: PathBuf,
    files: Vec<PathBuf>,
    time: f64,
}

/// One evaluation: the mapping drives, the queries and their ground truth.
struct Job<'a> {
    references: Vec<&'a ReferenceDrive>,
    query: &'a Path,
    query_files: &'a [PathBuf],
    ground_truth: &'a GroundTruth,
}

/// Metric fields averaged over the folds of `--leave-one-out`.
const METRIC_FIELDS: [&str; 5] = [
    "ap",
    "recall_at_100p",
    "recall_at_99p",
    "max_f1",
    "precision_at_full",
];

/// Runs `eval` and returns the JSON report.
pub fn run(args: &EvalArgs) -> Result<Value> {
    let started = Instant::now();
    args.solver.to_params()?;
    Exclusions::parse(&args.exclude)?;
    for out in [&args.predictions, &args.plot, &args.save_similarity]
        .into_iter()
        .flatten()
    {
        check_output_location(out)?;
    }
    let mut methods = vec![args.method];
    methods.extend(args.compare.iter().copied().filter(|m| *m != args.method));
    if args.reference.len() > 1 {
        if let Some(m) = methods.iter().find(|m| !m.is_cooc()) {
            bail!(
                "--reference is given {} times, but `{}` localizes against one reference \
                 folder; only the co-occurrence methods (cooc, cooc-seq, cooc-flow) fuse \
                 several mapping drives",
                args.reference.len(),
                m.name()
            );
        }
    }
    if !args.reference_time.is_empty() && args.reference_time.len() != args.reference.len() {
        bail!(
            "--reference-time is given {} times for {} --reference folders: give one time per \
             drive, in the same order, or none",
            args.reference_time.len(),
            args.reference.len()
        );
    }
    if let Some(t) = args.reference_time.iter().find(|t| !t.is_finite()) {
        bail!("--reference-time must be a finite number, got {t}");
    }
    let drives = reference_drives(args)?;
    if args.leave_one_out {
        return leave_one_out(args, &drives, started);
    }
    let (Some(query), Some(gt_path)) = (&args.query, &args.ground_truth) else {
        bail!("--query and --ground-truth are required (unless --leave-one-out)");
    };
    let ground_truth = GroundTruth::from_csv(gt_path)?;
    let query_files = list_images(query)?;
    check_ground_truth(&ground_truth, gt_path, query, query_files.len())?;
    let job = Job {
        references: drives.iter().collect(),
        query,
        query_files: &query_files,
        ground_truth: &ground_truth,
    };
    run_job(args, &methods, &job, started)
}

/// The `--reference` folders with their images and times, every drive with the same count.
fn reference_drives(args: &EvalArgs) -> Result<Vec<ReferenceDrive>> {
    let mut drives: Vec<ReferenceDrive> = Vec::with_capacity(args.reference.len());
    for (k, folder) in args.reference.iter().enumerate() {
        let files = list_images(folder)?;
        if let Some(first) = drives.first() {
            if files.len() != first.files.len() {
                return Err(Error::Shape(format!(
                    "--reference {}: {} images, but the first drive {} has {}; image k of \
                     every mapping drive is location k, so all drives need the same count",
                    folder.display(),
                    files.len(),
                    first.folder.display(),
                    first.files.len()
                ))
                .into());
            }
        }
        drives.push(ReferenceDrive {
            folder: folder.clone(),
            files,
            time: args.reference_time.get(k).copied().unwrap_or(k as f64),
        });
    }
    Ok(drives)
}

fn check_ground_truth(gt: &GroundTruth, path: &Path, query: &Path, queries: usize) -> Result<()> {
    if let Some(q) = gt.max_query_index() {
        if q >= queries {
            bail!(
                "{}: names query {q} but {} has only {queries} images",
                path.display(),
                query.display(),
            );
        }
    }
    Ok(())
}

/// The paper's protocol: each `--reference` folder in turn is the query, the others the map.
fn leave_one_out(args: &EvalArgs, drives: &[ReferenceDrive], started: Instant) -> Result<Value> {
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
            let gt = GroundTruth::from_csv(path)?;
            check_ground_truth(&gt, path, &drives[0].folder, locations)?;
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

/// Scores `methods` on one evaluation and returns its JSON report.
fn run_job(args: &EvalArgs, methods: &[Method], job: &Job, started: Instant) -> Result<Value> {
    let solver = args.solver.to_params()?;
    let exclusions = Exclusions::parse(&args.exclude)?;
    let ground_truth = job.ground_truth;
    let query_files = job.query_files;
    let reference_files = &job.references[0].files;
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
            format!(
                "the map's input geometry ({}x{} px, {})",
                first.0,
                first.1,
                match args.descriptor.resize {
                    Some(_) => "--resize".to_string(),
                    None => format!("the first reference image {}", first_file.display()),
                }
            )
        })?;
        let references = extract("reference", extractor.as_ref(), reference_files)?;
        let queries = extract("query", extractor.as_ref(), query_files)?;
        shapes = json!({"descriptor": args.descriptor.label(), "descriptor_dim": queries.cols()});
        if args.descriptor.descriptor == super::DescriptorKind::Hog {
            let (w, h) = args.descriptor.resize.unwrap_or(first);
            shapes["input_geometry"] = json!([w, h]);
            shapes["fit"] = json!(crate::features::Fit::from(args.descriptor.fit).name());
        }
        let ts = Instant::now();
        let c = cosine_matrix(&queries, &references)?;
        let chat = Normalization::apply(args.normalization.into(), &c)?;
        similarity_seconds = ts.elapsed().as_secs_f64();
        if let Some(path) = &args.save_similarity {
            super::npy::write_matrix(path, &c)?;
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
            Some(super::cooc::build_map(params, &drives, query_files)?)
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

    let options = LocalizeOptions {
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
    };
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
    Ok(report)
}

fn run_method(
    method: Method,
    inputs: &Inputs,
    options: &LocalizeOptions,
    cooc_options: &CoocOptions,
) -> Result<(Vec<Prediction>, Value)> {
    let flow_params = |solution: &crate::solver::Solution| {
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

fn method_json(method: Method, m: &Metrics, extra: &Value, solve_seconds: f64) -> Value {
    let mut v = json!({
        "method": method.name(),
        "ap": m.ap,
        "recall_at_100p": m.recall_at_100p,
        "recall_at_99p": m.recall_at_99p,
        "max_f1": m.max_f1,
        "precision_at_full": m.precision_at_full,
        "predicted": m.predicted,
        "correct": m.correct,
        "positives": m.positives,
        "seconds": {"solve": solve_seconds},
    });
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

fn check_output_location(path: &Path) -> Result<()> {
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if !parent.is_dir() {
        bail!(
            "{}: the folder {} does not exist",
            path.display(),
            parent.display()
        );
    }
    Ok(())
}

fn dir_name(path: &Path) -> String {
    path.file_name().map_or_else(
        || path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    )
}
