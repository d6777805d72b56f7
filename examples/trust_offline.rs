//! The offline side of the trust harness: each of `check_trust.py`'s derived routes (for any
//! region of Nordland, or Gardens Point night on a day map) localized as `seasonloc eval` does
//! (flow, HOG, claim = tolerance) with `F = 1` and `F = 2`, and dumped per prediction with its
//! evidence ([`seasonloc_core::calibration::PredictionEvidence`]) and the truth; SeqSLAM's
//! predictions on the same route beside them, and each route's metrics on stderr.
//!
//! Run:
//! `cargo run --release --example trust_offline -- nordland DIR START LEN OUT.csv`
//! `cargo run --release --example trust_offline -- gardens DIR day_right|day_left OUT.csv`

use std::io::Write;
use std::path::PathBuf;

use seasonloc_core::baselines::{seqslam, SeqSlamParams};
use seasonloc_core::calibration::{prediction_evidence, relative_column_means};
use seasonloc_core::eval::{evaluate, Exclusions, GroundTruth};
use seasonloc_core::localize::{solve_ranked, LocalizeOptions, Prediction};
use seasonloc_core::similarity::{cosine_matrix, Normalization};
use seasonloc_core::solver::SolverParams;

#[path = "support/trust_routes.rs"]
mod trust_routes;

fn f(x: f64) -> String {
    if x.is_nan() {
        "nan".into()
    } else if x.is_infinite() {
        if x > 0.0 { "inf" } else { "-inf" }.into()
    } else {
        format!("{x:.6}")
    }
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: trust_offline nordland DIR START LEN OUT.csv | gardens DIR day_right|day_left OUT.csv";
    let (region, out) = match args.first().map(String::as_str) {
        Some("nordland") if args.len() == 5 => {
            let start: usize = args[2].parse().expect(usage);
            let len: usize = args[3].parse().expect(usage);
            (
                trust_routes::nordland(&PathBuf::from(&args[1]), start, len),
                &args[4],
            )
        }
        Some("gardens") if args.len() == 4 => (
            trust_routes::gardens_point(&PathBuf::from(&args[1]), &args[2]),
            &args[3],
        ),
        _ => panic!("{usage}"),
    };
    let tol = region.tolerance;
    let mut w = std::io::BufWriter::new(std::fs::File::create(out).expect("output file"));
    writeln!(w, "region,route,method,query,truth,ref,confidence,right,tol,rank,ratio,contrast,stretch_centered,stretch_min,step_mean,step_spread,chat,chat_of_best,best_offset,stake,hidden_cost,hidden_ratio,column").unwrap();
    for route in &region.routes {
        let q = region.queries(route);
        let c = cosine_matrix(&q, &region.map).expect("cosine");
        let chat = Normalization::default().apply(&c).expect("normalise");
        let gt = GroundTruth::from_pairs(
            route
                .truth
                .iter()
                .enumerate()
                .filter_map(|(i, t)| t.map(|t| (i, t))),
        );
        let score = |p: &[Prediction]| {
            evaluate(p, &gt, route.frames.len(), tol, &Exclusions::none()).expect("scorable")
        };
        let truth = |i: usize| route.truth[i];
        let right = |i: usize, j: usize| truth(i).is_some_and(|t| t.abs_diff(j) <= tol);
        for flows in [1usize, 2] {
            let options = LocalizeOptions {
                solver: SolverParams {
                    flows,
                    ..SolverParams::default()
                },
                claim: tol,
                ..LocalizeOptions::default()
            };
            let (solution, ranked) = solve_ranked(&chat, &options).expect("solve");
            let len = options.confidence.stretch_len();
            let column = relative_column_means(&c);
            let ev = prediction_evidence(
                &chat,
                &ranked,
                Some(&column),
                solution.hidden_cost,
                len,
                options.confidence.radius,
            );
            for e in &ev {
                writeln!(
                    w,
                    "{},{},flow{flows},{},{},{},{},{},{tol},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
                    region.name,
                    route.name,
                    e.query,
                    truth(e.query).map_or(-1, |t| t as i64),
                    e.reference,
                    f(e.ratio),
                    u8::from(right(e.query, e.reference)),
                    e.rank,
                    f(e.ratio),
                    f(e.contrast),
                    f(e.stretch_centered),
                    f(e.stretch_min),
                    f(e.step_mean),
                    f(e.step_spread),
                    f(e.chat),
                    f(e.chat_of_best),
                    e.best_offset,
                    f(e.stake),
                    f(solution.hidden_cost),
                    f(e.hidden_ratio),
                    f(e.column),
                )
                .unwrap();
            }
            let preds: Vec<Prediction> = ranked.iter().map(|r| r.prediction).collect();
            let m = score(&preds);
            eprintln!(
                "{} / {} / flow F={flows}: AP {:.3} R@99 {:.3} ({} predictions)",
                region.name,
                route.name,
                m.ap,
                m.recall_at_99p,
                preds.len()
            );
        }
        let ss = seqslam(&c, &SeqSlamParams::default()).expect("seqslam");
        for p in &ss {
            writeln!(
                w,
                "{},{},seqslam,{},{},{},{},{},{tol},0,nan,nan,nan,nan,nan,nan,nan,nan,0,nan,nan,nan,nan",
                region.name,
                route.name,
                p.query,
                truth(p.query).map_or(-1, |t| t as i64),
                p.reference,
                f(p.confidence),
                u8::from(right(p.query, p.reference)),
            )
            .unwrap();
        }
        let m = score(&ss);
        eprintln!(
            "{} / {} / seqslam: AP {:.3} R@99 {:.3}",
            region.name, route.name, m.ap, m.recall_at_99p
        );
    }
}
