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
//!
//! Code: this file holds the arguments, their checks and the reference drives;
//! `eval/job.rs` one evaluation (descriptors and/or the co-occurrence map, every method
//! scored, the report) and `eval/leave_one_out.rs` the protocol that runs one per fold.

use std::path::{Path, PathBuf};
use std::time::Instant;

use super::NormalizationArg;
use anyhow::{bail, Result};
use clap::{Args, ValueEnum};
use serde_json::Value;

use super::cooc::CoocArgs;
use super::ground_truth;
use super::{DescriptorArgs, SolverArgs};
use seasonloc_core::cooc::CoocMethod;
use seasonloc_core::eval::{utm_of_files, Exclusions, GroundTruth, GroundTruthFiles};
use seasonloc_core::features::list_images;
use seasonloc_core::Error;

mod descriptors;
mod job;
mod leave_one_out;

pub use job::metrics_json;
use job::{run_job, Job};
use leave_one_out::leave_one_out;

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
    /// The discounted min-marginal ratio (default; `O(Q·D)` in total; trips score with its
    /// causal form).
    Discounted,
    /// The local min-marginal ratio on the 11-row box window (the default of earlier versions).
    Window,
}

/// Flags of `seasonloc eval`.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Folder of reference (map) images, taken in file-name order. The co-occurrence methods
    /// fuse several mapping drives of one route: repeat the flag (image k of every drive =
    /// location k).
    #[arg(long, required_unless_present = "reference_descriptors")]
    pub reference: Vec<PathBuf>,
    /// Reference descriptors (one row per map image, in route order) from a float32/float64
    /// `.npy` instead of `--reference` images: the descriptor methods (flow, best-match,
    /// seqslam) on descriptors from any network. Needs `--query-descriptors`.
    #[arg(long, requires = "query_descriptors", conflicts_with_all = ["reference", "query"])]
    pub reference_descriptors: Option<PathBuf>,
    /// Query descriptors (one row per query image, in driving order), `.npy`, with
    /// `--reference-descriptors`.
    #[arg(long, requires = "reference_descriptors")]
    pub query_descriptors: Option<PathBuf>,
    /// Time of day of each `--reference` drive (repeat once per drive, same order; any number
    /// whose order is the drives' order in time, e.g. hours), for the co-occurrence map's
    /// interpolation between drives adjacent in time. Default: the order given.
    #[arg(long, allow_negative_numbers = true)]
    pub reference_time: Vec<f64>,
    /// Folder of query images, taken in file-name order.
    #[arg(long)]
    pub query: Option<PathBuf>,
    /// Ground truth: a CSV with a header holding at least `query_index,ref_index`; VPR-Bench's
    /// `ground_truth_new.npy` (rows `[query, [refs]]`); VPR_Tutorial's GThard as a bool
    /// references x queries `.npy`, or a `.npz` holding `GThard` (see docs/metrics.md).
    /// Optional with `--leave-one-out`, where it defaults to query k -> location k.
    #[arg(long)]
    pub ground_truth: Option<PathBuf>,
    /// With a `.npz` ground truth: read its `GTsoft` instead of `GThard`.
    #[arg(long)]
    pub soft_ground_truth: bool,
    /// The ground truth from VPR-methods-evaluation's layout instead of --ground-truth: the UTM
    /// coordinates in the reference and query file names (`@east@north@...`), a reference true
    /// within this many metres of the query (that project uses 25).
    #[arg(long, conflicts_with = "ground_truth")]
    pub positive_distance: Option<f64>,
    /// Refuse (exit non-zero) a ground truth whose `query_file` / `ref_file` columns name other
    /// files than the folders' files at those indices; without it that is a warning on stderr.
    #[arg(long)]
    pub strict: bool,
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
    /// Write `query_index,ref_index,confidence,p_correct` of the main method here.
    #[arg(long)]
    pub predictions: Option<PathBuf>,
    /// Write the reliability diagram of the main method's `p_correct` here (`.png`): per bin of
    /// predicted probability, the fraction of predictions that are right.
    #[arg(long)]
    pub reliability: Option<PathBuf>,
    /// Write a precision-recall plot of all scored methods here (`.png`, or `.jpg`).
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
    /// `O(Q·D)` in total; trips score with its causal form) or `window` (the 11-row box window
    /// of earlier versions; `12·D` work per matched row).
    #[arg(long, value_enum, default_value_t = ConfidenceArg::Discounted)]
    pub confidence: ConfidenceArg,
    /// Flow confidence `discounted`: the weight `G` of a row one frame further away, 0 < G < 1.
    #[arg(long, default_value_t = seasonloc_core::confidence::DEFAULT_DISCOUNT)]
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

/// One mapping drive: its folder, its images in file-name order and its time key.
struct ReferenceDrive {
    folder: PathBuf,
    files: Vec<PathBuf>,
    time: f64,
}

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
    if let Some(plot) = &args.plot {
        // Checked before the run: the plot is drawn last, and the image encoder only knows
        // the formats this build decodes.
        let ext = plot
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        if !matches!(ext.as_deref(), Some("png" | "jpg" | "jpeg")) {
            bail!(
                "--plot {}: the plot is a PNG or JPEG image, name it *.png (or *.jpg)",
                plot.display()
            );
        }
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
    if !args.reference_time.is_empty() && !methods.iter().any(|m| m.is_cooc()) {
        bail!(
            "--reference-time orders the mapping drives of a co-occurrence map; `{}` does not \
             use it (score cooc, cooc-seq or cooc-flow, or leave it out)",
            args.method.name()
        );
    }
    if let Some(reference) = &args.reference_descriptors {
        return descriptors::run(args, reference, &methods, started);
    }
    let drives = reference_drives(args)?;
    if args.leave_one_out {
        return leave_one_out(args, &drives, started);
    }
    let (Some(query), true) = (
        &args.query,
        args.ground_truth.is_some() || args.positive_distance.is_some(),
    ) else {
        bail!("--query and --ground-truth are required (unless --leave-one-out)");
    };
    let query_files = list_images(query)?;
    let ground_truth = match (&args.ground_truth, args.positive_distance) {
        (Some(gt_path), _) => {
            let gt = ground_truth::load(gt_path, args.soft_ground_truth)?;
            check_ground_truth(
                &gt,
                gt_path,
                (query, query_files.len()),
                (&drives[0].folder, drives[0].files.len()),
            )?;
            if ground_truth::Form::of(gt_path) == ground_truth::Form::Csv {
                check_file_names(gt_path, &query_files, &drives[0].files, args.strict)?;
            }
            gt
        }
        (None, Some(metres)) => GroundTruth::within_distance(
            &utm_of_files(&drives[0].files)?,
            &utm_of_files(&query_files)?,
            metres,
        )?,
        (None, None) => bail!("--query and --ground-truth are required (unless --leave-one-out)"),
    };
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

/// Every index the ground truth at `path` names must be an image of its folder: `query` and
/// `reference` are each a folder with its image count.
fn check_ground_truth(
    gt: &GroundTruth,
    path: &Path,
    query: (&Path, usize),
    reference: (&Path, usize),
) -> Result<()> {
    let checks = [
        ("query", gt.max_query_index(), query),
        ("reference", gt.max_reference_index(), reference),
    ];
    for (what, max, (folder, count)) in checks {
        if let Some(i) = max {
            if i >= count {
                bail!(
                    "{}: names {what} {i} but {} has only {count} images",
                    path.display(),
                    folder.display(),
                );
            }
        }
    }
    Ok(())
}

/// Compares the ground truth's file columns with the folders (`eval::GroundTruthFiles`): rows
/// naming other files are a warning on stderr, or with `--strict` an error.
fn check_file_names(
    gt_path: &Path,
    queries: &[PathBuf],
    references: &[PathBuf],
    strict: bool,
) -> Result<()> {
    let check = GroundTruthFiles::from_csv(gt_path)?.check(queries, references);
    if check.holds() {
        return Ok(());
    }
    let what = format!(
        "ground truth {}: {} of its {} rows with file columns name files that are not the          folders' files at their index ({}); it may belong to other folders or another dataset",
        gt_path.display(),
        check.mismatched,
        check.checked,
        check.first.as_deref().unwrap_or("")
    );
    if strict {
        bail!("{what} (--strict)");
    }
    eprintln!("warning: {what}; scoring anyway (--strict refuses it)");
    Ok(())
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
