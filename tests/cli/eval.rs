//! `seasonloc eval` on generated image routes: its outputs, images of any size brought to the
//! map's geometry, and every bad input answered in one line before any work.

use crate::common::{npy_f32, seasonloc, write_route, Dir};

#[test]
fn eval_localizes_a_generated_route_and_writes_its_outputs() {
    let dir = Dir::new();
    let route = write_route(&dir, 40, 30);
    let preds = dir.path("out/p.csv");
    let plot = dir.path("out/pr.png");
    let reliability = dir.path("out/reliability.png");
    std::fs::create_dir_all(dir.path("out")).unwrap();
    let out = seasonloc(&[
        "eval",
        "--reference",
        &route.reference,
        "--query",
        &route.query,
        "--ground-truth",
        &route.ground_truth,
        "--cell-size",
        "8",
        "--tolerance",
        "1",
        "--compare",
        "best-match,seqslam",
        "--predictions",
        preds.to_str().unwrap(),
        "--plot",
        plot.to_str().unwrap(),
        "--reliability",
        reliability.to_str().unwrap(),
    ])
    .success_json();
    assert_eq!(out["method"], "flow");
    assert_eq!(out["queries"], 30);
    assert_eq!(out["references"], 40);
    for key in [
        "ap",
        "recall_at_100p",
        "recall_at_99p",
        "max_f1",
        "precision_at_full",
    ] {
        let v = out[key].as_f64().unwrap_or(-1.0);
        assert!((0.0..=1.0).contains(&v), "{key} = {v}");
    }
    assert!(
        out["ap"].as_f64().unwrap() > 0.9,
        "the generated route is easy: {out}"
    );
    for stage in ["features", "similarity", "solve"] {
        assert!(out["seconds"][stage].as_f64().is_some(), "{out}");
    }
    let compared: Vec<&str> = out["compared"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["method"].as_str().unwrap())
        .collect();
    assert_eq!(compared, vec!["best-match", "seqslam"]);
    let csv = std::fs::read_to_string(&preds).unwrap();
    assert!(
        csv.starts_with("query_index,ref_index,confidence,p_correct\n"),
        "{csv}"
    );
    assert!(csv.lines().count() > 20);
    // Every flow prediction has a calibrated probability.
    for line in csv.lines().skip(1) {
        let p: f64 = line.rsplit(',').next().unwrap().parse().unwrap();
        assert!((0.0..=1.0).contains(&p), "{line}");
    }
    let png = std::fs::read(&plot).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    // The reliability diagram of p_correct, and its figures in the report.
    let png = std::fs::read(&reliability).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    let cal = &out["calibration"];
    let ece = cal["ece"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&ece), "{cal}");
    let bins = cal["bins"].as_array().unwrap();
    assert_eq!(bins.len(), 10, "{cal}");
    let counted: u64 = bins.iter().map(|b| b["count"].as_u64().unwrap()).sum();
    assert_eq!(counted, out["predicted"].as_u64().unwrap(), "{cal}");
    assert!(cal["ranked_by_p_correct"]["ap"].as_f64().is_some(), "{cal}");
}

/// A reliability diagram needs a calibrated method: asked of one without `p_correct`, eval
/// says so in one line.
#[test]
fn eval_reliability_needs_a_calibrated_method() {
    let dir = Dir::new();
    let route = write_route(&dir, 20, 10);
    let out = seasonloc(&[
        "eval",
        "--reference",
        &route.reference,
        "--query",
        &route.query,
        "--ground-truth",
        &route.ground_truth,
        "--cell-size",
        "8",
        "--method",
        "best-match",
        "--reliability",
        dir.path("r.png").to_str().unwrap(),
    ]);
    out.failure_mentions("--reliability: method `best-match` gives no p_correct");
}

#[test]
fn eval_rejects_bad_input_with_one_line() {
    let dir = Dir::new();
    let route = write_route(&dir, 10, 10);
    std::fs::create_dir_all(dir.path("empty")).unwrap();
    let empty = dir.path("empty");
    let odd = dir.path("odd");
    std::fs::create_dir_all(&odd).unwrap();
    image::RgbImage::new(64, 32)
        .save(odd.join("a.png"))
        .unwrap();
    image::RgbImage::new(48, 32)
        .save(odd.join("b.png"))
        .unwrap();
    // A first reference image smaller than one HOG cell cannot set the input geometry.
    let tiny = dir.path("tiny");
    std::fs::create_dir_all(&tiny).unwrap();
    // Each bad folder holds as many images as the route's references (the ground truth's
    // indices fit), the bad one first: its own error is the one to name.
    let fill = |folder: &std::path::Path| {
        for k in 1..10 {
            image::RgbImage::new(64, 32)
                .save(folder.join(format!("z{k}.png")))
                .unwrap();
        }
    };
    image::RgbImage::new(4, 4).save(tiny.join("a.png")).unwrap();
    fill(&tiny);
    let corrupt = dir.path("corrupt");
    std::fs::create_dir_all(&corrupt).unwrap();
    std::fs::write(corrupt.join("x.png"), b"\x89PNG but not really").unwrap();
    fill(&corrupt);
    let base2 = |r: &str, q: &str| -> Vec<String> {
        [
            "eval",
            "--reference",
            r,
            "--query",
            q,
            "--ground-truth",
            &route.ground_truth,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    let base = |q: &str| base2(&route.reference, q);
    let with = |mut v: Vec<String>, extra: &[&str]| {
        v.extend(extra.iter().map(|s| s.to_string()));
        v
    };
    let cases: Vec<(Vec<String>, &str)> = vec![
        (base(dir.path("nope").to_str().unwrap()), "nope"),
        (base(empty.to_str().unwrap()), "empty"),
        (base2(tiny.to_str().unwrap(), &route.query), "a.png"),
        (
            with(
                base2(odd.to_str().unwrap(), &route.query),
                &["--fit", "zoom"],
            ),
            "--fit",
        ),
        (base2(corrupt.to_str().unwrap(), &route.query), "x.png"),
        (with(base(&route.query), &["--flows", "abc"]), "--flows"),
        (
            with(base(&route.query), &["--tolerance", "-1"]),
            "--tolerance",
        ),
        (vec!["eval".to_string()], "--reference"),
        (with(base(&route.query), &["--exclude", "5-2"]), "exclude"),
        (
            with(base(&route.query), &["--exclude", "0-100"]),
            "nothing to score: no query left after --exclude 0-100 has a ground-truth match",
        ),
        (with(base(&route.query), &["--cell-size", "1"]), "cell_size"),
        (
            with(base(&route.query), &["--plot", "/no/such/dir/p.png"]),
            "/no/such/dir",
        ),
        // Refused before the run, not by the encoder at its end.
        (
            with(
                base(&route.query),
                &["--plot", dir.path("p.svg").to_str().unwrap()],
            ),
            "name it *.png",
        ),
        // A missing model is the CNN's problem, not the input geometry's.
        (
            with(
                base(&route.query),
                &["--descriptor", "cnn", "--cnn-model", "/no/such/m.onnx"],
            ),
            "--descriptor cnn: /no/such/m.onnx",
        ),
        (
            {
                let mut v = base(&route.query);
                let gt = v.iter().position(|a| a == "--ground-truth").unwrap() + 1;
                v[gt] = dir.path("missing.csv").to_str().unwrap().to_string();
                v
            },
            "missing.csv",
        ),
        (
            {
                let far = dir.path("far.csv");
                std::fs::write(&far, "query_index,ref_index\n0,50\n").unwrap();
                let mut v = base(&route.query);
                let gt = v.iter().position(|a| a == "--ground-truth").unwrap() + 1;
                v[gt] = far.to_str().unwrap().to_string();
                v
            },
            "names reference 50 but",
        ),
    ];
    for (args, needle) in cases {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        seasonloc(&args).failure_mentions(needle);
    }
}

/// Query images of another size or aspect ratio than the map's are brought to the map's input
/// geometry (its first reference image's size) without any flag, by `--fit` stretch or crop.
#[test]
fn eval_brings_images_of_any_size_to_the_map_geometry() {
    let dir = Dir::new();
    let route = write_route(&dir, 40, 30);
    let resized = |name: &str, (w, h): (u32, u32), pad: u32| {
        let out = dir.path(name);
        std::fs::create_dir_all(&out).unwrap();
        for entry in std::fs::read_dir(&route.query).unwrap() {
            let path = entry.unwrap().path();
            let img = image::open(&path).unwrap().to_rgb8();
            let big = image::imageops::resize(&img, w, h, image::imageops::FilterType::Triangle);
            // `pad` grey rows above and below: another camera with a taller field of view.
            let mut framed = image::RgbImage::from_pixel(w, h + 2 * pad, image::Rgb([90; 3]));
            image::imageops::replace(&mut framed, &big, 0, i64::from(pad));
            framed.save(out.join(path.file_name().unwrap())).unwrap();
        }
        out.to_str().unwrap().to_string()
    };
    let twice = resized("query-128x64", (128, 64), 0);
    let taller = resized("query-96x64", (96, 48), 8);
    let run = |query: &str, extra: &[&str]| {
        let mut args = vec![
            "eval",
            "--reference",
            &route.reference,
            "--query",
            query,
            "--ground-truth",
            &route.ground_truth,
            "--cell-size",
            "8",
            "--tolerance",
            "1",
        ];
        args.extend_from_slice(extra);
        seasonloc(&args).success_json()
    };
    let same = run(&route.query, &[]);
    let out = run(&twice, &[]);
    assert_eq!(out["input_geometry"], serde_json::json!([64, 32]), "{out}");
    assert_eq!(out["fit"], "stretch");
    assert_eq!(out["descriptor_dim"], same["descriptor_dim"]);
    assert!(out["ap"].as_f64().unwrap() > 0.9, "{out}");
    // 96x64 with 8 px bands: the centred 2:1 window is the scene; crop finds it.
    let crop = run(&taller, &["--fit", "crop"]);
    assert_eq!(crop["fit"], "crop");
    assert!(crop["ap"].as_f64().unwrap() > 0.9, "{crop}");
    // An explicit --resize is the geometry instead.
    let explicit = run(&twice, &["--resize", "32x16"]);
    assert_eq!(explicit["input_geometry"], serde_json::json!([32, 16]));
}

/// Issue 42, silent mistake S1: a ground truth whose `query_file` / `ref_file` columns name
/// other files than the folders' (here another dataset's `night_right/Image000.jpg`) is scored
/// with a warning on stderr naming the first such row, and refused with `--strict`; one naming
/// the folders' own files passes `--strict` without a warning. Before, both ran silently.
#[test]
fn a_ground_truth_naming_other_files_warns_and_strict_refuses_it() {
    let dir = Dir::new();
    let route = write_route(&dir, 24, 16);
    let write = |name: &str, row: &dyn Fn(usize) -> String| {
        let mut text = String::from("query_index,query_file,ref_index,ref_file\n");
        for k in 0..16 {
            text.push_str(&format!("{k},{}\n", row(k)));
        }
        let path = dir.path(name);
        std::fs::write(&path, text).unwrap();
        path.to_str().unwrap().to_string()
    };
    let own = write("own.csv", &|k| {
        format!("query/frame-{k:05}.png,{k},reference/frame-{k:05}.png")
    });
    let foreign = write("foreign.csv", &|k| {
        format!("night_right/Image{k:03}.jpg,{k},day_right/Image{k:03}.jpg")
    });
    let run = |gt: &str, strict: bool| {
        let mut args = vec![
            "eval",
            "--reference",
            &route.reference,
            "--query",
            &route.query,
            "--ground-truth",
            gt,
            "--cell-size",
            "8",
        ];
        if strict {
            args.push("--strict");
        }
        seasonloc(&args)
    };
    let warned = run(&foreign, false);
    warned.success_json();
    let stderr = String::from_utf8_lossy(&warned.output.stderr);
    assert!(
        stderr.contains("warning: ground truth")
            && stderr.contains("16 of its 16 rows")
            && stderr.contains("night_right/Image000.jpg")
            && stderr.contains("frame-00000.png"),
        "{stderr}"
    );
    run(&foreign, true).failure_mentions("query_file is `night_right/Image000.jpg`");
    let clean = run(&own, true);
    clean.success_json();
    let stderr = String::from_utf8_lossy(&clean.output.stderr);
    assert!(!stderr.contains("warning"), "{stderr}");
}

/// The field's ground-truth forms score as the equivalent CSV (`tests/data/gt_forms`: query q
/// has reference q, query 3 also 5, query 7 also 6), and `eval` prints Recall@N and the AUC.
#[test]
fn eval_reads_the_fields_ground_truth_forms_and_prints_their_metrics() {
    let dir = Dir::new();
    let route = write_route(&dir, 20, 10);
    let mut csv = String::from("query_index,ref_index\n");
    for q in 0..10 {
        csv.push_str(&format!("{q},{q}\n"));
    }
    csv.push_str("3,5\n7,6\n");
    let csv_path = dir.path("multi.csv");
    std::fs::write(&csv_path, csv).unwrap();
    let forms = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/gt_forms");
    let run = |gt: &str, extra: &[&str]| {
        let mut args = vec![
            "eval",
            "--reference",
            &route.reference,
            "--query",
            &route.query,
            "--ground-truth",
            gt,
            "--cell-size",
            "8",
            "--compare",
            "best-match",
        ];
        args.extend_from_slice(extra);
        seasonloc(&args).success_json()
    };
    let want = run(csv_path.to_str().unwrap(), &[]);
    let recall = &want["recall_at_n"];
    for n in ["1", "5", "10", "20"] {
        let r = recall[n].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&r), "{n}: {want}");
    }
    assert_eq!(
        recall["20"], 1.0,
        "20 references: every true match is in the top 20"
    );
    let auc = want["auc"].as_f64().unwrap();
    assert!(auc > 0.5 && auc <= 1.0, "{want}");
    assert!(want["compared"][0]["auc"].as_f64().is_some(), "{want}");
    let same = |got: &serde_json::Value| {
        for key in [
            "ap",
            "auc",
            "recall_at_100p",
            "recall_at_99p",
            "positives",
            "correct",
            "recall_at_n",
        ] {
            assert_eq!(got[key], want[key], "{key}");
        }
        assert_eq!(got["compared"][0]["ap"], want["compared"][0]["ap"]);
    };
    for file in ["ground_truth_new.npy", "GThard.npy", "GT.npz"] {
        same(&run(forms.join(file).to_str().unwrap(), &[]));
    }
    same(&run(
        forms.join("GT.npz").to_str().unwrap(),
        &["--soft-ground-truth"],
    ));
    // A ground truth that names more references than the folder holds is refused.
    let dir2 = Dir::new();
    let small = write_route(&dir2, 8, 8);
    seasonloc(&[
        "eval",
        "--reference",
        &small.reference,
        "--query",
        &small.query,
        "--ground-truth",
        forms.join("GThard.npy").to_str().unwrap(),
    ])
    .failure_mentions("names");
    std::fs::write(dir.path("junk.npy"), b"\x93NUMPY garbage").unwrap();
    seasonloc(&[
        "eval",
        "--reference",
        &route.reference,
        "--query",
        &route.query,
        "--ground-truth",
        dir.path("junk.npy").to_str().unwrap(),
    ])
    .failure_mentions("junk.npy");
}

/// VPR-methods-evaluation's layout: UTM coordinates in the file names, true within
/// `--positive-distance` metres, the same scores as the CSV of the same pairs.
#[test]
fn eval_takes_the_ground_truth_from_utm_file_names() {
    let dir = Dir::new();
    let route = write_route(&dir, 12, 12);
    for (from, to, offset) in [
        (&route.reference, "database", 0.0),
        (&route.query, "queries", 3.0),
    ] {
        let to = dir.path(to);
        std::fs::create_dir_all(&to).unwrap();
        let mut files: Vec<_> = std::fs::read_dir(from)
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        files.sort();
        for (i, f) in files.iter().enumerate() {
            let east = 500_000.0 + 20.0 * i as f64 + offset;
            let name = format!("@{east:.2}@4000000.00@33@T@0@0@@@@@@@.png");
            std::fs::copy(f, to.join(name)).unwrap();
        }
    }
    let (db, qs) = (dir.path("database"), dir.path("queries"));
    let base = [
        "eval",
        "--reference",
        db.to_str().unwrap(),
        "--query",
        qs.to_str().unwrap(),
        "--cell-size",
        "8",
    ];
    let utm = seasonloc(&[&base[..], &["--positive-distance", "5"]].concat()).success_json();
    let csv =
        seasonloc(&[&base[..], &["--ground-truth", &route.ground_truth]].concat()).success_json();
    for key in ["ap", "auc", "positives", "recall_at_n"] {
        assert_eq!(utm[key], csv[key], "{key}");
    }
    // 25 m reaches the neighbours (17 and 23 m away) too: more true matches.
    let wide = seasonloc(&[&base[..], &["--positive-distance", "25"]].concat()).success_json();
    assert!(
        wide["recall_at_n"]["1"].as_f64() >= csv["recall_at_n"]["1"].as_f64(),
        "{wide}"
    );
    seasonloc(
        &[
            &base[..],
            &[
                "--positive-distance",
                "5",
                "--ground-truth",
                &route.ground_truth,
            ],
        ]
        .concat(),
    )
    .failure_mentions("--positive-distance");
    seasonloc(&[
        "eval",
        "--reference",
        &route.reference,
        "--query",
        &route.query,
        "--positive-distance",
        "5",
    ])
    .failure_mentions("UTM");
}

/// `--reference-descriptors` / `--query-descriptors`: the descriptor methods on `.npy`
/// descriptors from any network, with every ground-truth form and the same report.
#[test]
fn eval_scores_descriptors_from_npy_files() {
    let dir = Dir::new();
    let (refs, queries, dim) = (30usize, 20usize, 16usize);
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    let r: Vec<f32> = (0..refs * dim).map(|_| next()).collect();
    // Query q shows reference q + 5, with noise.
    let q: Vec<f32> = (0..queries * dim)
        .map(|k| r[(k / dim + 5) * dim + k % dim] + 0.1 * next())
        .collect();
    let (rp, qp) = (dir.path("r.npy"), dir.path("q.npy"));
    npy_f32(&rp, refs, dim, &r);
    npy_f32(&qp, queries, dim, &q);
    let gt = dir.path("gt.csv");
    let rows: String = (0..queries).map(|i| format!("{i},{}\n", i + 5)).collect();
    std::fs::write(&gt, format!("query_index,ref_index\n{rows}")).unwrap();
    let args = [
        "eval",
        "--reference-descriptors",
        rp.to_str().unwrap(),
        "--query-descriptors",
        qp.to_str().unwrap(),
        "--ground-truth",
        gt.to_str().unwrap(),
        "--compare",
        "best-match,seqslam",
    ];
    let out = seasonloc(&args).success_json();
    assert_eq!(out["method"], "flow");
    assert_eq!(
        (out["queries"].as_u64(), out["references"].as_u64()),
        (Some(20), Some(30))
    );
    assert!(out["ap"].as_f64().unwrap() > 0.8, "{out}");
    assert_eq!(out["recall_at_n"]["1"], 1.0, "{out}");
    assert_eq!(out["compared"][0]["method"], "best-match");
    assert_eq!(out["compared"][0]["ap"], 1.0, "{out}");
    seasonloc(&[&args[..], &["--method", "cooc"]].concat()).failure_mentions("needs images");
    seasonloc(&args[..3]).failure_mentions("--query-descriptors");
    let bad = dir.path("bad.csv");
    std::fs::write(&bad, "query_index,ref_index\n25,0\n").unwrap();
    seasonloc(&[&args[..5], &["--ground-truth", bad.to_str().unwrap()]].concat())
        .failure_mentions("names query 25");
}
