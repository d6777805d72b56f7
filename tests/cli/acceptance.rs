//! The acceptance numbers on the shared data, through `seasonloc eval` as the README runs it:
//! Nordland dev (issue 14's bars) and every Gardens Point pairing. Skipped with a message when
//! `../shared/data` is absent.

use crate::common::{seasonloc, shared};
use serde_json::Value;

/// The acceptance numbers on the shared Nordland split (winter queries against the summer map,
/// tolerance 1, queries 0-16 excluded, HOG with 8 px cells, every other setting at its default:
/// the README's command), issue 14's bars: AP >= 0.85, recall at 99 % precision >= 0.80 and
/// ahead of SeqSLAM's, the flow ahead of both baselines, and a second flow not lowering AP.
#[test]
fn nordland_flow_beats_the_baselines_with_a_trustworthy_confidence() {
    let Some(data) = shared("data/nordland_64x32") else {
        return;
    };
    let d = |p: &str| data.join(p).to_str().unwrap().to_string();
    let run = |flows: &str| {
        seasonloc(&[
            "eval",
            "--reference",
            &d("summer"),
            "--query",
            &d("winter"),
            "--ground-truth",
            &d("ground_truth.csv"),
            "--tolerance",
            "1",
            "--exclude",
            "0-16",
            "--cell-size",
            "8",
            "--flows",
            flows,
            "--compare",
            "best-match,seqslam",
        ])
        .success_json()
    };
    let out = run("1");
    let (ap, r99) = (metric(&out, "ap"), metric(&out, "recall_at_99p"));
    let compared = out["compared"].as_array().unwrap();
    let (best_match, seqslam) = (&compared[0], &compared[1]);
    eprintln!(
        "flow AP {ap:.4} R@99 {r99:.4}; best match AP {:.4}; SeqSLAM AP {:.4} R@99 {:.4}",
        metric(best_match, "ap"),
        metric(seqslam, "ap"),
        metric(seqslam, "recall_at_99p")
    );
    assert!(ap >= 0.85, "{out}");
    assert!(r99 >= 0.80, "{out}");
    assert!(r99 > metric(seqslam, "recall_at_99p"), "{out}");
    assert!(
        ap > metric(best_match, "ap") && ap > metric(seqslam, "ap"),
        "{out}"
    );
    let two = run("2");
    eprintln!("F = 2: AP {:.4}", metric(&two, "ap"));
    assert!(metric(&two, "ap") >= ap, "F = 2 lowers AP: {two}");
}

/// A number of an `eval` report (the main method's, or one of `compared`).
fn metric(report: &Value, name: &str) -> f64 {
    report[name]
        .as_f64()
        .unwrap_or_else(|| panic!("no {name} in {report}"))
}

/// Every Gardens Point pairing of the README (day_right map against night_right and day_left
/// queries, day_left map against night_right; HOG, and the CNN when `../shared/models` holds
/// it), run as the README runs them: no `--resize`, so the 640x360 night frames are brought to
/// the day walks' 960x540 by the input-geometry rule. In every pairing the flow is ahead of
/// SeqSLAM and best match, a second flow does not lower its AP, and it keeps AP within about
/// 0.05 of the README's table (the floors below).
#[test]
fn gardens_point_every_pairing_runs_at_any_size_and_the_flow_leads() {
    let Some(data) = shared("data/gardenspoint_dev") else {
        return;
    };
    let d = |p: &str| data.join(p).to_str().unwrap().to_string();
    let night_gt = "gt_night_right_vs_day_right.csv";
    // (map, queries, ground truth, HOG floor, CNN floor); README: HOG 0.936, 0.797, 0.508;
    // CNN 1.000, 0.876, 0.778.
    let pairings = [
        ("day_right", "night_right", night_gt, 0.90, 0.95),
        (
            "day_right",
            "day_left",
            "gt_day_left_vs_day_right.csv",
            0.75,
            0.82,
        ),
        ("day_left", "night_right", night_gt, 0.45, 0.72),
    ];
    let model = shared("models/efficientnet-lite0-224.onnx");
    let model = model.as_ref().map(|m| m.to_str().unwrap().to_string());
    for (map, queries, gt, hog_floor, cnn_floor) in pairings {
        let mut descriptors = vec![("HOG", vec![], hog_floor)];
        if let Some(m) = &model {
            let cnn = [
                "--descriptor",
                "cnn",
                "--cnn-model",
                m,
                "--cnn-layer",
                "block10",
            ];
            descriptors.push(("CNN", cnn.map(String::from).to_vec(), cnn_floor));
        }
        for (name, extra, floor) in descriptors {
            let run = |flows: &str| {
                let (reference, query, truth) = (d(map), d(queries), d(gt));
                let mut args = vec![
                    "eval",
                    "--reference",
                    &reference,
                    "--query",
                    &query,
                    "--ground-truth",
                    &truth,
                    "--tolerance",
                    "2",
                    "--flows",
                    flows,
                    "--compare",
                    "best-match,seqslam",
                ];
                args.extend(extra.iter().map(String::as_str));
                seasonloc(&args).success_json()
            };
            let out = run("1");
            let ap = metric(&out, "ap");
            let compared = out["compared"].as_array().unwrap();
            let (best_match, seqslam) = (metric(&compared[0], "ap"), metric(&compared[1], "ap"));
            let two = metric(&run("2"), "ap");
            eprintln!(
                "{map} vs {queries}, {name}: flow AP {ap:.3} (F = 2: {two:.3}), SeqSLAM {seqslam:.3}, best match {best_match:.3}"
            );
            if name == "HOG" {
                assert_eq!(
                    out["input_geometry"],
                    serde_json::json!([960, 540]),
                    "{out}"
                );
            }
            assert!(ap >= floor, "{map} vs {queries}, {name}: {out}");
            assert!(
                ap > seqslam && ap > best_match,
                "{map} vs {queries}, {name}: {out}"
            );
            assert!(
                two >= ap,
                "{map} vs {queries}, {name}: F = 2 AP {two} < {ap}"
            );
        }
    }
}
