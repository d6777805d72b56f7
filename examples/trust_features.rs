//! The trust harness: drives trips in process exactly as the outside trust check (`check_trust.py`) does
//! over HTTP (batches of 10, trip defaults; Nordland HOG 8 px, Gardens Point HOG 32 px) on the
//! check's derived routes, for any region of Nordland, and dumps per frame, at arrival (the
//! batch's answer) and final (after the lag window), the estimate, the trip's evidence
//! ([`seasonloc_core::trip::FrameEvidence`]) and the truth.
//!
//! Run:
//! `cargo run --release --example trust_features -- nordland DIR START LEN OUT.csv`
//! `cargo run --release --example trust_features -- gardens DIR day_right|day_left OUT.csv`
//!
//! Columns: `region, route, when (arrival|final), frame, truth (-1 off the map), ref (-1
//! none), confidence, right (ref within the tolerance), tol`, the evidence fields, and two
//! history columns (`changes`: times the frame's reference moved by more than the tolerance
//! between re-traces; `arrival_ref`).

use std::io::Write;
use std::path::PathBuf;

use seasonloc_core::similarity::cosine_matrix;
use seasonloc_core::trip::column_prior;

#[path = "support/trust_routes.rs"]
mod trust_routes;
use trust_routes::{drive, Region, Route, Seen};

fn f(x: f64) -> String {
    if x.is_nan() {
        "nan".into()
    } else if x.is_infinite() {
        if x > 0.0 { "inf" } else { "-inf" }.into()
    } else {
        format!("{x:.6}")
    }
}

pub const HEADER: &str = "region,route,when,frame,truth,ref,confidence,right,tol,path_ref,ratio,hidden_ratio,stake,contrast,stretch_trailing,stretch_min,marked,later,since_jump,hidden_trailing,step_mean,step_spread,chat,chat_of_best,best_offset,prior,hidden_cost,stretch_local,ratio_before,ratio_after,log_ratio_local,dwell,row_scale,row_median,changes,arrival_ref,p_correct,status";

fn line(
    region: &Region,
    route: &Route,
    when: &str,
    i: usize,
    s: &Seen,
    changes: usize,
    arrival_ref: Option<usize>,
) -> String {
    let truth = route.truth[i];
    let e = &s.estimate;
    let right = match (truth, e.reference) {
        (Some(t), Some(j)) => t.abs_diff(j) <= region.tolerance,
        _ => false,
    };
    let opt = |x: Option<usize>| x.map_or("-1".to_string(), |v| v.to_string());
    let ev = s.evidence.expect("evidence for every reported frame");
    format!(
        "{},{},{when},{i},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{changes},{},{},{}",
        region.name,
        route.name,
        opt(truth),
        opt(e.reference),
        f(e.confidence),
        u8::from(right),
        region.tolerance,
        opt(ev.path_reference),
        f(ev.ratio),
        f(ev.hidden_ratio),
        f(ev.stake),
        f(ev.contrast),
        f(ev.stretch_trailing),
        f(ev.stretch_min),
        u8::from(ev.marked),
        ev.later,
        ev.since_jump,
        ev.hidden_trailing,
        f(ev.step_mean),
        f(ev.step_spread),
        f(ev.chat),
        f(ev.chat_of_best),
        ev.best_offset,
        f(ev.prior),
        f(ev.hidden_cost),
        f(ev.stretch_local),
        f(ev.ratio_before),
        f(ev.ratio_after),
        f(ev.log_ratio_local),
        ev.dwell,
        f(ev.row_scale),
        f(ev.row_median),
        opt(arrival_ref),
        f(e.p_correct),
        e.status.as_str(),
    )
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: trust_features nordland DIR START LEN OUT.csv | gardens DIR day_right|day_left OUT.csv";
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
    // Per map place: the prior over its median and its "twin" (the most similar map place
    // more than 10 places away), for exploring distinctiveness.
    {
        let prior = column_prior(&region.map).expect("prior");
        let mut sorted = prior.clone();
        sorted.sort_by(f32::total_cmp);
        let med = sorted[sorted.len() / 2];
        let cc = cosine_matrix(&region.map, &region.map).expect("cosine");
        let mut pw = std::io::BufWriter::new(
            std::fs::File::create(format!("{out}.places.csv")).expect("places file"),
        );
        writeln!(pw, "region,ref,prior_rel,twin").unwrap();
        for (j, &pj) in prior.iter().enumerate() {
            let twin = (0..region.map.rows())
                .filter(|&k| k.abs_diff(j) > 10)
                .map(|k| cc.get(j, k))
                .fold(f32::NEG_INFINITY, f32::max);
            writeln!(pw, "{},{j},{},{twin}", region.name, pj / med).unwrap();
        }
    }
    let mut w = std::io::BufWriter::new(std::fs::File::create(out).expect("output file"));
    writeln!(w, "{HEADER}").unwrap();
    for route in &region.routes {
        let t = std::time::Instant::now();
        // Trips opened with the region's tolerance, as check_trust.py opens them.
        // `TRUST_RELOCALIZATION=R` (research): another relocalization cost.
        let relocalization = match std::env::var("TRUST_RELOCALIZATION") {
            Ok(r) => Some(r.parse().expect("a relocalization cost")),
            Err(_) => seasonloc_core::trip::TripParams::default().relocalization,
        };
        let params = seasonloc_core::trip::TripParams {
            tolerance: region.tolerance,
            relocalization,
            ..seasonloc_core::trip::TripParams::default()
        };
        let frames = drive(&region, route, params);
        for (i, (a, l, changes)) in frames.iter().enumerate() {
            writeln!(w, "{}", line(&region, route, "arrival", i, a, 0, None)).unwrap();
            writeln!(
                w,
                "{}",
                line(
                    &region,
                    route,
                    "final",
                    i,
                    l,
                    *changes,
                    a.estimate.reference
                )
            )
            .unwrap();
        }
        eprintln!(
            "{} / {}: {} frames in {:.1} s",
            region.name,
            route.name,
            frames.len(),
            t.elapsed().as_secs_f64()
        );
    }
}
