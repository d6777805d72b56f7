//! `seasonloc eval --reference-descriptors R.npy --query-descriptors Q.npy`: the descriptor
//! methods scored on descriptors computed elsewhere (any network), with no images: the same
//! similarity, methods, metrics and report as an evaluation of image folders
//! ([`super::job`]), without the features stage, the plots' titles' folders or file checks.

use std::path::Path;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use serde_json::{json, Value};

use super::job::{localize_options, method_json, run_method, Inputs};
use super::{check_ground_truth, EvalArgs, Method};
use crate::cli::{ground_truth, npy};
use seasonloc_core::cooc::CoocOptions;
use seasonloc_core::eval::{evaluate, recall_at_n, write_predictions_csv, Exclusions, STANDARD_NS};
use seasonloc_core::similarity::{cosine_matrix, Normalization};

/// Scores `methods` on the descriptors in `reference` and `--query-descriptors`.
pub(super) fn run(
    args: &EvalArgs,
    reference: &Path,
    methods: &[Method],
    started: Instant,
) -> Result<Value> {
    if let Some(m) = methods.iter().find(|m| m.is_cooc()) {
        bail!(
            "--reference-descriptors: `{}` needs images (the co-occurrence methods use local \
             features); score flow, best-match or seqslam",
            m.name()
        );
    }
    for (flag, set) in [
        ("--plot", args.plot.is_some()),
        ("--reliability", args.reliability.is_some()),
        ("--leave-one-out", args.leave_one_out),
    ] {
        if set {
            bail!("{flag} needs image folders; it does not apply to --reference-descriptors");
        }
    }
    let query = args
        .query_descriptors
        .as_deref()
        .context("--reference-descriptors needs --query-descriptors")?;
    let solver = args.solver.to_params()?;
    let exclusions = Exclusions::parse(&args.exclude)?;
    let (gt_path, gt) = match &args.ground_truth {
        Some(p) => (p, ground_truth::load(p, args.soft_ground_truth)?),
        None => bail!("--reference-descriptors needs --ground-truth"),
    };
    let references = npy::read_matrix(reference)?;
    let queries = npy::read_matrix(query)?;
    check_ground_truth(
        &gt,
        gt_path,
        (query, queries.rows()),
        (reference, references.rows()),
    )?;
    let t = Instant::now();
    let c = cosine_matrix(&queries, &references)?;
    let chat = Normalization::apply(args.normalization.into(), &c)?;
    let similarity_seconds = t.elapsed().as_secs_f64();
    if let Some(path) = &args.save_similarity {
        npy::write_matrix(path, &c)?;
    }
    let recalls = recall_at_n(&c, &gt, &STANDARD_NS, args.tolerance, &exclusions)?;
    let inputs = Inputs {
        descriptors: Some((c, chat)),
        cooc: None,
    };
    let options = localize_options(args, solver);
    let cooc_options = CoocOptions::default();
    let mut reports = Vec::new();
    for (k, &method) in methods.iter().enumerate() {
        let t = Instant::now();
        let (predictions, extra) = run_method(method, &inputs, &options, &cooc_options)?;
        let seconds = t.elapsed().as_secs_f64();
        let metrics = evaluate(
            &predictions,
            &gt,
            queries.rows(),
            args.tolerance,
            &exclusions,
        )?;
        if k == 0 {
            if let Some(path) = &args.predictions {
                write_predictions_csv(path, &predictions)?;
            }
        }
        reports.push(method_json(method, &metrics, &extra, seconds));
    }
    let mut report = reports.remove(0);
    let obj = report
        .as_object_mut()
        .context("method report is an object")?;
    obj.insert("descriptor".into(), json!("npy"));
    obj.insert("descriptor_dim".into(), json!(queries.cols()));
    obj.insert("queries".into(), json!(queries.rows()));
    obj.insert("references".into(), json!(references.rows()));
    obj.insert("tolerance".into(), json!(args.tolerance));
    obj.insert("exclude".into(), json!(args.exclude));
    obj.insert(
        "normalization".into(),
        json!(format!("{:?}", args.normalization).to_lowercase()),
    );
    obj.insert(
        "recall_at_n".into(),
        Value::Object(
            recalls
                .iter()
                .map(|r| (r.n.to_string(), json!(r.recall)))
                .collect(),
        ),
    );
    obj.insert(
        "seconds".into(),
        json!({"similarity": similarity_seconds, "total": started.elapsed().as_secs_f64()}),
    );
    obj.insert("compared".into(), Value::Array(reports));
    Ok(report)
}
