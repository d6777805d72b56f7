//! Regenerates the shipped calibration (`src/calibration/fitted.rs`) from the dev data and
//! prints the check on data the fit never sees.
//!
//! * **Fit**: the derived routes of the outside trust check (straight, speed changes
//!   and stops, a loop, a detour through unmapped frames, past the map's end) built from
//!   Nordland frames 1200-2399: map summer 1200-2199, off-map frames 2200-2375. Trips exactly
//!   as the check drives them (HOG 8 px, batches of 10, trip defaults), every frame at arrival
//!   and final; offline, each route localized as `seasonloc eval` does (claim = tolerance) with
//!   `F = 1` and `F = 2`. Labels at tolerance 1 and 2 (the models take the tolerance).
//! * **Check**: the same routes on Nordland frames 17-1192 (the check's own region) and Gardens
//!   Point night on the day_right and day_left walks (HOG 32 px, tolerance 2): an unseen
//!   part of the route and an unseen dataset.
//! * **Designs**: (A) isotonic regression (pool-adjacent-violators) of the log ratio alone,
//!   (B) logistic regression (Newton, L2 1) on [`seasonloc_core::calibration::trip_features`] /
//!   [`seasonloc_core::calibration::offline_features`]. B is what ships.
//!
//! Run: `cargo run --release --example calibrate [-- NORDLAND_DIR GARDENS_DIR] [--write]`
//! (default: where the tests find the datasets); `--write` rewrites
//! `crates/core/src/calibration/fitted.rs`.
//! Prints per route, at arrival and final: precision and coverage of `p >= 0.9`, off-map frames
//! with `p >= 0.9`, first localized frame after a return to the map; pooled ECE (10 bins,
//! off-map frames with a reference count as wrong) and the reliability bins; offline AP and
//! recall at 99 % precision ranked by `p` against the ratio and SeqSLAM.

use std::fmt::Write as _;
use std::path::PathBuf;

use seasonloc_core::baselines::{seqslam, SeqSlamParams};
use seasonloc_core::calibration::fit::{
    expected_calibration_error, fit_isotonic, fit_logistic, reliability, Isotonic, Logistic,
};
use seasonloc_core::calibration::{
    offline_features, prediction_evidence, relative_column_means, trip_features,
    OFFLINE_FEATURE_NAMES, RATIO_SEGMENTS, TRIP_FEATURE_NAMES,
};
use seasonloc_core::eval::{evaluate, Exclusions, GroundTruth};
use seasonloc_core::localize::{solve_ranked, LocalizeOptions, Prediction};
use seasonloc_core::similarity::{cosine_matrix, Normalization};
use seasonloc_core::solver::SolverParams;
use seasonloc_core::trip::TripParams;

#[path = "support/trust_routes.rs"]
mod trust_routes;
use trust_routes::{drive, Region};

/// The threshold of `localized`.
const THRESHOLD: f64 = 0.9;
/// Tolerances the models are fitted on.
const FIT_TOLERANCES: [usize; 2] = [1, 2];

/// One trip frame estimate with a reference: what it says and what is true.
struct TripSample {
    region: String,
    route: String,
    arrival: bool,
    frame: usize,
    features: Vec<f64>,
    reference: Option<usize>,
    truth: Option<usize>,
    tolerance: usize,
}

impl TripSample {
    fn right_at(&self, tol: usize) -> bool {
        matches!((self.reference, self.truth), (Some(j), Some(t)) if j.abs_diff(t) <= tol)
    }
}

/// One offline prediction.
struct OfflineSample {
    region: String,
    route: String,
    flows: usize,
    prediction: Prediction,
    features: Vec<f64>,
    truth: Option<usize>,
    tolerance: usize,
}

impl OfflineSample {
    fn right_at(&self, tol: usize) -> bool {
        self.truth
            .is_some_and(|t| t.abs_diff(self.prediction.reference) <= tol)
    }
}

/// The trip samples of every route of `region` (every frame, at arrival and final; frames
/// without a reference too, their features unused).
fn trip_samples(region: &Region) -> Vec<TripSample> {
    let mut out = Vec::new();
    for route in &region.routes {
        for (i, (arrival, last, _)) in drive(region, route, TripParams::default())
            .iter()
            .enumerate()
        {
            for (seen, is_arrival) in [(arrival, true), (last, false)] {
                let ev = seen.evidence.expect("evidence for every frame");
                out.push(TripSample {
                    region: region.name.clone(),
                    route: route.name.clone(),
                    arrival: is_arrival,
                    frame: i,
                    features: trip_features(&ev, region.tolerance).to_vec(),
                    reference: seen.estimate.reference,
                    truth: route.truth[i],
                    tolerance: region.tolerance,
                });
            }
        }
    }
    out
}

/// The offline samples of every route of `region` with `F = 1` and `F = 2`, and SeqSLAM's
/// predictions per route.
fn offline_samples(region: &Region) -> (Vec<OfflineSample>, Vec<(String, Vec<Prediction>)>) {
    let tol = region.tolerance;
    let mut out = Vec::new();
    let mut ss = Vec::new();
    for route in &region.routes {
        let q = region.queries(route);
        let c = cosine_matrix(&q, &region.map).expect("cosine");
        let chat = Normalization::default().apply(&c).expect("normalise");
        let column = relative_column_means(&c);
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
            let ev = prediction_evidence(
                &chat,
                &ranked,
                Some(&column),
                solution.hidden_cost,
                options.confidence.stretch_len(),
                options.confidence.radius,
            );
            for (r, e) in ranked.iter().zip(&ev) {
                out.push(OfflineSample {
                    region: region.name.clone(),
                    route: route.name.clone(),
                    flows,
                    prediction: r.prediction,
                    features: offline_features(e, tol).to_vec(),
                    truth: route.truth[r.prediction.query],
                    tolerance: tol,
                });
            }
        }
        ss.push((
            route.name.clone(),
            seqslam(&c, &SeqSlamParams::default()).expect("seqslam"),
        ));
    }
    (out, ss)
}

/// A calibration design: a fitted model that maps features to `p`.
enum Design {
    /// Isotonic regression of the log ratio (the sum of its segments, features 0-2).
    A(Isotonic),
    /// Logistic regression on all features.
    B(Logistic),
}

impl Design {
    fn p(&self, x: &[f64]) -> f64 {
        match self {
            // A step function ties whole blocks; the log ratio orders within them (by at
            // most 1e-8, so the calibration is unchanged and the ranking is the ratio's).
            Design::A(m) => {
                let l = x[0] + x[1] + x[2];
                (m.predict(l) + 1e-9 * l).clamp(0.0, 1.0)
            }
            Design::B(m) => m.predict(x),
        }
    }
}

/// Fits both designs on `(features, label at tolerance t)` for the fitting tolerances (A on
/// tolerance 1 only: it has no tolerance input).
fn fit_designs(rows: &[(Vec<f64>, Vec<bool>)], tol_index: usize) -> (Design, Design) {
    let (mut x, mut y) = (Vec::new(), Vec::new());
    for (f, labels) in rows {
        for (k, &t) in FIT_TOLERANCES.iter().enumerate() {
            let mut f = f.clone();
            f[tol_index] = (t as f64).ln();
            x.push(f);
            y.push(labels[k]);
        }
    }
    let w = vec![1.0; x.len()];
    // The ratio's segment slopes stay >= 0 (active set: a segment whose slope comes out
    // negative is held at 0 and the rest refitted), so p never falls as the ratio rises.
    let mut held: Vec<usize> = Vec::new();
    let b = loop {
        let b = fit_logistic(&x, &y, &w, 1.0).expect("a fit");
        let negative: Vec<usize> = RATIO_SEGMENTS
            .iter()
            .copied()
            .filter(|&k| b.coefficients[k + 1] < 0.0 && !held.contains(&k))
            .collect();
        if negative.is_empty() {
            break b;
        }
        held.extend(negative);
        for f in &mut x {
            for &k in &held {
                f[k] = 0.0;
            }
        }
    };
    let s: Vec<f64> = rows.iter().map(|(f, _)| f[0] + f[1] + f[2]).collect();
    let y1: Vec<bool> = rows.iter().map(|(_, l)| l[0]).collect();
    let a = fit_isotonic(&s, &y1, &vec![1.0; s.len()]);
    (Design::A(a), Design::B(b))
}

/// Precision, coverage and off-map share of `localized` (`p >= THRESHOLD` with a reference)
/// over trip samples.
fn trip_scores(samples: &[&TripSample], p: &[f64]) -> (f64, f64, f64, usize) {
    let on = samples.iter().filter(|s| s.truth.is_some()).count();
    let off = samples.len() - on;
    let (mut loc, mut right, mut off_loc) = (0, 0, 0);
    for (s, &p) in samples.iter().zip(p) {
        if s.reference.is_some() && p >= THRESHOLD {
            loc += 1;
            if s.right_at(s.tolerance) {
                right += 1;
            }
            if s.truth.is_none() {
                off_loc += 1;
            }
        }
    }
    let ratio = |a: usize, b: usize, empty: f64| if b > 0 { a as f64 / b as f64 } else { empty };
    (
        ratio(right, loc, 1.0),
        ratio(right, on, 1.0),
        ratio(off_loc, off, 0.0),
        loc,
    )
}

/// The frames after a route's return to the map until the first right `localized` frame.
fn return_delay(samples: &[&TripSample], p: &[f64], back: usize) -> Option<usize> {
    samples
        .iter()
        .zip(p)
        .filter(|(s, &p)| {
            s.frame >= back && s.reference.is_some() && p >= THRESHOLD && s.right_at(s.tolerance)
        })
        .map(|(s, _)| s.frame - back)
        .min()
}

/// Where a route returns to the map after leaving it (loop: drives back; detour: returns).
fn return_frame(route: &str, len: usize) -> Option<usize> {
    match route {
        "loop" => Some(600 * len / 1000),
        "detour" => Some(400 * len / 1000 + 60),
        _ => None,
    }
}

/// The trip report of one design over some samples; returns the pooled ECE at arrival and
/// final.
fn trip_report(
    out: &mut String,
    name: &str,
    design: &Design,
    samples: &[TripSample],
    bins: bool,
) -> (f64, f64) {
    let p: Vec<f64> = samples
        .iter()
        .map(|s| {
            if s.reference.is_some() {
                design.p(&s.features)
            } else {
                0.0
            }
        })
        .collect();
    let mut keys: Vec<(String, String)> = Vec::new();
    for s in samples {
        let k = (s.region.clone(), s.route.clone());
        if !keys.contains(&k) {
            keys.push(k);
        }
    }
    let _ = writeln!(out, "  {name}: route | precision arrival / final | coverage arrival / final | off-map localized arrival / final | first localized after the return, arrival / final");
    for (region, route) in &keys {
        let mut line = format!("    {region} {route}:");
        let mut delays = Vec::new();
        let mut cells = Vec::new();
        for arrival in [true, false] {
            let idx: Vec<usize> = (0..samples.len())
                .filter(|&i| {
                    let s = &samples[i];
                    &s.region == region && &s.route == route && s.arrival == arrival
                })
                .collect();
            let ss: Vec<&TripSample> = idx.iter().map(|&i| &samples[i]).collect();
            let pp: Vec<f64> = idx.iter().map(|&i| p[i]).collect();
            cells.push(trip_scores(&ss, &pp));
            let len = if region.starts_with("nordland") {
                1000
            } else {
                100
            };
            if let Some(back) = return_frame(route, len) {
                delays.push(return_delay(&ss, &pp, back));
            }
        }
        let (a, f) = (cells[0], cells[1]);
        let _ = write!(
            line,
            " P {:.3} / {:.3} | C {:.3} / {:.3} | off {:.3} / {:.3}",
            a.0, f.0, a.1, f.1, a.2, f.2
        );
        if !delays.is_empty() {
            let _ = write!(line, " | back after {:?} / {:?}", delays[0], delays[1]);
        }
        let _ = writeln!(out, "{line}");
    }
    let pairs = |arrival: bool| -> Vec<(f64, bool)> {
        samples
            .iter()
            .zip(&p)
            .filter(|(s, _)| s.arrival == arrival && s.reference.is_some())
            .map(|(s, &p)| (p, s.right_at(s.tolerance)))
            .collect()
    };
    let (ea, ef) = (
        expected_calibration_error(&pairs(true), 10),
        expected_calibration_error(&pairs(false), 10),
    );
    let _ = writeln!(
        out,
        "    pooled ECE (10 bins): arrival {ea:.3}, final {ef:.3}"
    );
    if bins {
        for (when, arrival) in [("arrival", true), ("final", false)] {
            let r = reliability(&pairs(arrival), 10);
            let cells: Vec<String> = r
                .iter()
                .map(|b| {
                    format!(
                        "{:.1}-{:.1}: n {} p {:.3} obs {:.3}",
                        b.lo, b.hi, b.count, b.predicted, b.observed
                    )
                })
                .collect();
            let _ = writeln!(out, "    reliability {when}: {}", cells.join("; "));
        }
    }
    (ea, ef)
}

/// AP and recall at 99 % precision (spec §4) of a route's predictions.
fn ap_r99(preds: &[Prediction], gt: &GroundTruth, frames: usize, tol: usize) -> (f64, f64) {
    let m = evaluate(preds, gt, frames, tol, &Exclusions::none()).expect("scorable");
    (m.ap, m.recall_at_99p)
}

/// A route's samples with `confidence` replaced (the ratio, or `p`).
fn with_confidence(s: &[&OfflineSample], confidence: &[f64]) -> Vec<Prediction> {
    s.iter()
        .zip(confidence)
        .map(|(s, &c)| Prediction {
            confidence: c,
            ..s.prediction
        })
        .collect()
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let write = args.iter().any(|a| a == "--write");
    let dirs: Vec<&String> = args.iter().filter(|a| !a.starts_with("--")).collect();
    let nordland = dirs
        .first()
        .map(PathBuf::from)
        .or_else(seasonloc_test_support::datasets::nordland)
        .expect("the Nordland dev folder (give it as the first argument)");
    let gardens = dirs
        .get(1)
        .map(PathBuf::from)
        .or_else(seasonloc_test_support::datasets::gardens_point)
        .expect("the Gardens Point dev folder (give it as the second argument)");
    let t0 = std::time::Instant::now();
    let fit_region = trust_routes::nordland(&nordland, 1200, 1000);
    let check_regions = vec![
        trust_routes::nordland(&nordland, 17, 1000),
        trust_routes::gardens_point(&gardens, "day_right"),
        trust_routes::gardens_point(&gardens, "day_left"),
    ];
    eprintln!("descriptors in {:.1} s", t0.elapsed().as_secs_f64());

    // Trips.
    let fit_trips = trip_samples(&fit_region);
    let check_trips: Vec<TripSample> = check_regions.iter().flat_map(trip_samples).collect();
    let tol_index = TRIP_FEATURE_NAMES.len() - 1;
    let rows: Vec<(Vec<f64>, Vec<bool>)> = fit_trips
        .iter()
        .filter(|s| s.reference.is_some())
        .map(|s| {
            (
                s.features.clone(),
                FIT_TOLERANCES.iter().map(|&t| s.right_at(t)).collect(),
            )
        })
        .collect();
    let (trip_a, trip_b) = fit_designs(&rows, tol_index);
    let mut out = String::new();
    let _ = writeln!(out, "# Trips ({} fit samples with a reference)", rows.len());
    for (name, d) in [
        ("A (isotonic on the ratio)", &trip_a),
        ("B (logistic)", &trip_b),
    ] {
        let _ = writeln!(out, "## design {name}\n  fit (Nordland 1200-2399):");
        trip_report(&mut out, "fit", d, &fit_trips, false);
        let _ = writeln!(out, "  check (Nordland 17-1192, Gardens Point):");
        trip_report(&mut out, "check", d, &check_trips, true);
    }

    // Offline.
    let (fit_off, fit_ss) = offline_samples(&fit_region);
    let mut check_off = Vec::new();
    let mut check_ss = Vec::new();
    for r in &check_regions {
        let (o, s) = offline_samples(r);
        check_off.extend(o);
        check_ss.extend(
            s.into_iter()
                .map(|(route, p)| (format!("{} {route}", r.name), p)),
        );
    }
    let tol_index = OFFLINE_FEATURE_NAMES.len() - 1;
    let rows: Vec<(Vec<f64>, Vec<bool>)> = fit_off
        .iter()
        .map(|s| {
            (
                s.features.clone(),
                FIT_TOLERANCES.iter().map(|&t| s.right_at(t)).collect(),
            )
        })
        .collect();
    let (off_a, off_b) = fit_designs(&rows, tol_index);
    let _ = writeln!(out, "# Offline ({} fit predictions)", rows.len());
    let ss_named: Vec<(String, Vec<Prediction>)> = fit_ss
        .into_iter()
        .map(|(route, p)| (format!("{} {route}", fit_region.name), p))
        .chain(check_ss)
        .collect();
    for (name, d) in [
        ("A (isotonic on the ratio)", &off_a),
        ("B (logistic)", &off_b),
    ] {
        let _ = writeln!(out, "## design {name}: route | F | AP by ratio / by p | R@99 by ratio / by p | ECE | SeqSLAM R@99");
        for (label, samples) in [("fit", &fit_off), ("check", &check_off)] {
            let mut keys: Vec<(String, String)> = Vec::new();
            for s in samples.iter() {
                let k = (s.region.clone(), s.route.clone());
                if !keys.contains(&k) {
                    keys.push(k);
                }
            }
            let mut pooled: [Vec<(f64, bool)>; 2] = [Vec::new(), Vec::new()];
            for (region, route) in &keys {
                let regions: Vec<&Region> =
                    std::iter::once(&fit_region).chain(&check_regions).collect();
                let reg = regions.iter().find(|x| &x.name == region).expect("region");
                let rt = reg.routes.iter().find(|x| &x.name == route).expect("route");
                let gt = GroundTruth::from_pairs(
                    rt.truth
                        .iter()
                        .enumerate()
                        .filter_map(|(i, t)| t.map(|t| (i, t))),
                );
                let (frames, tol) = (rt.frames.len(), reg.tolerance);
                let ss_preds = ss_named
                    .iter()
                    .find(|(n, _)| n == &format!("{region} {route}"))
                    .map(|(_, p)| p.clone())
                    .unwrap_or_default();
                for flows in [1usize, 2] {
                    let s: Vec<&OfflineSample> = samples
                        .iter()
                        .filter(|s| &s.region == region && &s.route == route && s.flows == flows)
                        .collect();
                    let p: Vec<f64> = s.iter().map(|s| d.p(&s.features)).collect();
                    let ratio: Vec<f64> = s.iter().map(|s| s.prediction.confidence).collect();
                    let (ap_r, r_r) = ap_r99(&with_confidence(&s, &ratio), &gt, frames, tol);
                    let (ap_p, r_p) = ap_r99(&with_confidence(&s, &p), &gt, frames, tol);
                    let pairs: Vec<(f64, bool)> = s
                        .iter()
                        .zip(&p)
                        .map(|(s, &p)| (p, s.right_at(s.tolerance)))
                        .collect();
                    pooled[flows - 1].extend(&pairs);
                    let (_, ss_r) = ap_r99(&ss_preds, &gt, frames, tol);
                    let _ = writeln!(
                        out,
                        "    {label} {region} {route} F={flows}: AP {ap_r:.3} / {ap_p:.3} | R@99 {r_r:.3} / {r_p:.3} | ECE {:.3} | SeqSLAM {ss_r:.3}",
                        expected_calibration_error(&pairs, 10)
                    );
                }
            }
            let _ = writeln!(
                out,
                "    {label} pooled ECE: F=1 {:.3}, F=2 {:.3}",
                expected_calibration_error(&pooled[0], 10),
                expected_calibration_error(&pooled[1], 10)
            );
        }
    }
    print!("{out}");
    let Design::B(tb) = &trip_b else {
        unreachable!()
    };
    let Design::B(ob) = &off_b else {
        unreachable!()
    };
    // One value a line with its feature's name, the comments aligned as rustfmt aligns them.
    let list = |names: &[&str], b: &[f64]| -> String {
        let values: Vec<String> = b.iter().map(|v| format!("{v:.6},")).collect();
        let width = values.iter().map(String::len).max().unwrap_or(0) + 1;
        let mut s = String::new();
        for (v, n) in values
            .iter()
            .zip(std::iter::once(&"intercept").chain(names))
        {
            let _ = writeln!(s, "    {v:<width$}// {n}");
        }
        s
    };
    let source = format!(
        "//! The shipped calibration: generated by `cargo run --release --example calibrate -- --write`\n\
         //! (fit on the Nordland dev routes built from frames 1200-2399, tolerances 1 and 2); do\n\
         //! not edit by hand.\n\n\
         /// Trip model, intercept first, then one per [`super::TRIP_FEATURE_NAMES`].\n\
         pub(super) const TRIP_COEFFICIENTS: [f64; super::TRIP_FEATURES + 1] = [\n{}];\n\n\
         /// Offline model, intercept first, then one per [`super::OFFLINE_FEATURE_NAMES`].\n\
         pub(super) const OFFLINE_COEFFICIENTS: [f64; super::OFFLINE_FEATURES + 1] = [\n{}];\n",
        list(&TRIP_FEATURE_NAMES, &tb.coefficients),
        list(&OFFLINE_FEATURE_NAMES, &ob.coefficients)
    );
    if write {
        let path =
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("crates/core/src/calibration/fitted.rs");
        std::fs::write(&path, &source).expect("write fitted.rs");
        eprintln!("wrote {}", path.display());
    } else {
        println!("# fitted.rs (run with --write to ship)\n{source}");
    }
    eprintln!("({:.0} s)", t0.elapsed().as_secs_f64());
}
