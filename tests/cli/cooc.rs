//! `seasonloc eval` with the co-occurrence methods on generated routes: scoring from the
//! images, several mapping drives fused, leave-one-out, and their flags and drives checked
//! before any work.

use crate::common::{seasonloc, write_route, Dir};

#[test]
fn eval_scores_the_cooccurrence_methods_from_the_images() {
    let dir = Dir::new();
    let route = write_route(&dir, 40, 30);
    let preds = dir.path("p.csv");
    let out = seasonloc(&[
        "eval",
        "--reference",
        &route.reference,
        "--query",
        &route.query,
        "--ground-truth",
        &route.ground_truth,
        "--tolerance",
        "1",
        "--method",
        "cooc",
        "--compare",
        "cooc-seq,cooc-flow",
        "--seq-length",
        "5",
        "--predictions",
        preds.to_str().unwrap(),
    ])
    .success_json();
    eprintln!("{out:#}");
    assert_eq!(out["method"], "cooc");
    assert_eq!(out["descriptor"], "cooc");
    assert_eq!(out["queries"], 30);
    assert_eq!(out["references"], 40);
    // At most 16^2 words; fewer when the generated route has few distinct corners.
    let words = out["vocabulary_words"].as_u64().unwrap();
    assert!((16..=256).contains(&words), "{out}");
    let compared = out["compared"].as_array().unwrap();
    let names: Vec<&str> = compared
        .iter()
        .map(|c| c["method"].as_str().unwrap())
        .collect();
    assert_eq!(names, vec!["cooc-seq", "cooc-flow"]);
    assert_eq!(compared[0]["params"]["length"], 5);
    assert!(
        compared[1]["params"]["hidden_cost"].as_f64().is_some(),
        "{out}"
    );
    for m in std::iter::once(&out).chain(compared) {
        let ap = m["ap"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&ap), "{m}");
    }
    // The generated places are distinctive: the flow graph on co-occurrence scores finds the
    // route, and single images are mostly right.
    assert!(compared[1]["ap"].as_f64().unwrap() > 0.8, "{out}");
    assert!(out["correct"].as_u64().unwrap() >= 15, "{out}");
    assert!(
        out["seconds"]["similarity"].as_f64().unwrap() > 0.0,
        "{out}"
    );
    let csv = std::fs::read_to_string(&preds).unwrap();
    assert!(csv.lines().count() > 15, "{csv}");
}

/// A further traversal of `from`'s route under another light: every pixel `v -> f(v)`, same
/// file names (image k = location k).
fn write_traversal(dir: &Dir, from: &str, name: &str, f: impl Fn(u8) -> u8) -> String {
    let out = dir.path(name);
    std::fs::create_dir_all(&out).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let path = entry.unwrap().path();
        let mut img = image::open(&path).unwrap().to_rgb8();
        for px in img.pixels_mut() {
            *px = image::Rgb(px.0.map(&f));
        }
        img.save(out.join(path.file_name().unwrap())).unwrap();
    }
    out.to_str().unwrap().into()
}

#[test]
fn eval_fuses_several_mapping_drives_for_the_cooc_methods() {
    let dir = Dir::new();
    let route = write_route(&dir, 30, 30);
    let dusk = write_traversal(&dir, &route.reference, "dusk", |v| v / 2 + 20);
    let out = seasonloc(&[
        "eval",
        "--reference",
        &route.reference,
        "--reference",
        &dusk,
        "--reference-time",
        "12",
        "--reference-time",
        "18.5",
        "--query",
        &route.query,
        "--ground-truth",
        &route.ground_truth,
        "--tolerance",
        "1",
        "--method",
        "cooc",
        "--compare",
        "cooc-flow",
    ])
    .success_json();
    eprintln!("{out:#}");
    assert_eq!(out["references"], 30);
    let drives = out["drives"].as_array().unwrap();
    assert_eq!(drives.len(), 2);
    assert_eq!(drives[0]["folder"], route.reference.as_str());
    assert_eq!(drives[1]["folder"], dusk.as_str());
    assert_eq!(drives[1]["time"], 18.5);
    assert_eq!(out["query"], route.query.as_str());
    // Both drives are in the one fused map and the route is still found.
    assert!(out["compared"][0]["ap"].as_f64().unwrap() > 0.8, "{out}");
    assert!(out["correct"].as_u64().unwrap() >= 15, "{out}");
}

#[test]
fn eval_leave_one_out_scores_each_traversal_against_the_others() {
    let dir = Dir::new();
    let route = write_route(&dir, 30, 30);
    let dusk = write_traversal(&dir, &route.reference, "dusk", |v| v / 2 + 20);
    let traversals = [route.reference.as_str(), route.query.as_str(), &dusk];
    let out = seasonloc(&[
        "eval",
        "--reference",
        traversals[0],
        "--reference",
        traversals[1],
        "--reference",
        traversals[2],
        "--leave-one-out",
        "--tolerance",
        "1",
        "--method",
        "cooc",
        "--compare",
        "cooc-seq",
        "--seq-length",
        "5",
    ])
    .success_json();
    eprintln!("{out:#}");
    assert_eq!(out["protocol"], "leave-one-out");
    assert_eq!(out["method"], "cooc");
    assert_eq!(out["queries"], 90);
    let folds = out["folds"].as_array().unwrap();
    assert_eq!(folds.len(), 3);
    let mut ap_sum = 0.0;
    for (k, fold) in folds.iter().enumerate() {
        // Fold k: traversal k is the query, the other two the map (in the order given).
        assert_eq!(fold["query"], traversals[k]);
        let map: Vec<&str> = fold["drives"]
            .as_array()
            .unwrap()
            .iter()
            .map(|d| d["folder"].as_str().unwrap())
            .collect();
        let others: Vec<&str> = (0..3).filter(|&j| j != k).map(|j| traversals[j]).collect();
        assert_eq!(map, others);
        assert_eq!(fold["queries"], 30);
        // Query k -> location k by default: every traversal of these places is recognised.
        assert!(fold["correct"].as_u64().unwrap() >= 15, "{fold}");
        ap_sum += fold["ap"].as_f64().unwrap();
    }
    assert!(
        (out["ap"].as_f64().unwrap() - ap_sum / 3.0).abs() < 1e-9,
        "{out}"
    );
    assert_eq!(out["compared"][0]["method"], "cooc-seq");
    let seq_mean: f64 = folds
        .iter()
        .map(|f| f["compared"][0]["ap"].as_f64().unwrap())
        .sum::<f64>()
        / 3.0;
    assert!((out["compared"][0]["ap"].as_f64().unwrap() - seq_mean).abs() < 1e-9);
}

#[test]
fn eval_several_drives_are_checked_before_any_work() {
    let dir = Dir::new();
    let route = write_route(&dir, 6, 4);
    let eval = |extra: &[&str]| {
        let mut args = vec!["eval", "--reference", &route.reference];
        args.extend_from_slice(extra);
        seasonloc(&args)
    };
    let query = [
        "--query",
        &route.query,
        "--ground-truth",
        &route.ground_truth,
    ];
    // The query folder has 4 images, the first drive 6: the error names the drive.
    let mut two = vec!["--reference", &route.query, "--method", "cooc"];
    two.extend_from_slice(&query);
    eval(&two).failure_mentions(&format!("--reference {}: 4 images", route.query));
    // Only the co-occurrence methods fuse drives.
    let mut flow = vec!["--reference", &route.reference, "--method", "flow"];
    flow.extend_from_slice(&query);
    eval(&flow).failure_mentions("only the co-occurrence methods");
    let mut times = vec![
        "--reference-time",
        "1",
        "--reference-time",
        "2",
        "--method",
        "cooc",
    ];
    times.extend_from_slice(&query);
    eval(&times).failure_mentions("--reference-time");
    // A drive's time means nothing to the descriptor methods: refused, not ignored.
    let mut flow_time = vec!["--reference-time", "1", "--method", "flow"];
    flow_time.extend_from_slice(&query);
    eval(&flow_time).failure_mentions("does not use it");
    eval(&["--leave-one-out", "--method", "cooc"]).failure_mentions("at least two");
    eval(&["--method", "cooc"]).failure_mentions("--query");
    eval(&[
        "--reference",
        &route.reference,
        "--leave-one-out",
        "--method",
        "cooc",
        "--compare",
        "best-match",
    ])
    .failure_mentions("best-match");
}

#[test]
fn eval_cooc_flags_are_validated_before_any_work() {
    let dir = Dir::new();
    let route = write_route(&dir, 4, 3);
    let base = [
        "eval",
        "--reference",
        &route.reference,
        "--query",
        &route.query,
        "--ground-truth",
        &route.ground_truth,
        "--method",
        "cooc-seq",
    ];
    let with = |extra: &[&str]| {
        let mut args = base.to_vec();
        args.extend_from_slice(extra);
        seasonloc(&args)
    };
    with(&["--cooc-branching", "1"]).failure_mentions("vocabulary_branching");
    with(&["--seq-max-step", "0"]).failure_mentions("max_step");
    with(&["--save-similarity", dir.path("c.npy").to_str().unwrap()])
        .failure_mentions("--save-similarity");
}
