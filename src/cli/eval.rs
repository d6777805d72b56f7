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
    /// Folder of reference (map) images, taken in file-name order.
    #[arg(long)]
    pub reference: PathBuf,
    /// Folder of query images, taken in file-name order.
    #[arg(long)]
    pub query: PathBuf,
    /// Ground-truth CSV with a header holding at least `query_index,ref_index`.
    #[arg(long)]
    pub ground_truth: PathBuf,
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

/// Runs `eval` and returns the JSON report.
pub fn run(args: &EvalArgs) -> Result<Value> {
    let started = Instant::now();
    let solver = args.solver.to_params()?;
    let exclusions = Exclusions::parse(&args.exclude)?;
    for out in [&args.predictions, &args.plot, &args.save_similarity]
        .into_iter()
        .flatten()
    {
        check_output_location(out)?;
    }
    let ground_truth = GroundTruth::from_csv(&args.ground_truth)?;
    let reference_files = list_images(&args.reference)?;
    let query_files = list_images(&args.query)?;
    if let Some(q) = ground_truth.max_query_index() {
        if q >= query_files.len() {
            bail!(
                "{}: names query {q} but {} has only {} images",
                args.ground_truth.display(),
                args.query.display(),
                query_files.len()
            );
        }
    }

    let mut methods = vec![args.method];
    methods.extend(args.compare.iter().copied().filter(|m| *m != args.method));
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
        let references = extract("reference", extractor.as_ref(), &reference_files)?;
        let queries = extract("query", extractor.as_ref(), &query_files)?;
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
        Some(params) => Some(super::cooc::build_map(
            params,
            &reference_files,
            &query_files,
        )?),
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
    };
    let cooc_options = CoocOptions {
        sequence,
        flow: options.clone(),
    };
    let mut scored = Vec::new();
    for method in methods {
        let t = Instant::now();
        let (predictions, extra) = run_method(method, &inputs, &options, &cooc_options)?;
        let solve_seconds = t.elapsed().as_secs_f64();
        let metrics = evaluate(
            &predictions,
            &ground_truth,
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
            dir_name(&args.query),
            dir_name(&args.reference),
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
                json!({"length": s.length, "max_step": s.max_step, "exclusion": s.exclusion})
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
