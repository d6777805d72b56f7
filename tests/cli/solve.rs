//! `seasonloc solve`: generated `.npy` matrices (float32 and float64, a file or a pipe), the
//! spec's output shape, hidden rows, a second flow, and every bad input answered in one line.

use crate::common::{npy_f32, npy_f64, seasonloc, Dir};
use serde_json::Value;

#[test]
fn solve_follows_a_diagonal_and_reports_the_spec_shape() {
    let dir = Dir::new();
    // 4 queries x 6 references, a clear diagonal with a one-frame offset.
    let mut m = vec![0.5f32; 24];
    for i in 0..4 {
        m[i * 6 + i + 1] = 2.0;
    }
    let path = dir.path("s.npy");
    npy_f32(&path, 4, 6, &m);
    let out = seasonloc(&[
        "solve",
        "--similarity",
        path.to_str().unwrap(),
        "--hidden-cost",
        "1.5",
    ])
    .success_json();
    let hyps = out["hypotheses"].as_array().unwrap();
    assert_eq!(hyps.len(), 1);
    assert_eq!(hyps[0]["rank"], 1);
    let refs: Vec<i64> = hyps[0]["rows"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["matches"][0]["ref"].as_i64().unwrap())
        .collect();
    assert_eq!(refs, vec![1, 2, 3, 4]);
    assert!(
        (out["total_cost"].as_f64().unwrap() - 2.0).abs() < 1e-9,
        "{out}"
    );
    assert_eq!(out["predictions"].as_array().unwrap().len(), 4);
    assert_eq!(out["hidden_cost"], 1.5);
}

#[test]
fn solve_hides_rows_without_a_usable_match_and_reads_float64() {
    let dir = Dir::new();
    // Row 1 has only non-positive entries: it must be hidden.
    let m = [2.0, 0.5, 0.5, 0.0, -1.0, 0.0, 0.5, 0.5, 2.0];
    let path = dir.path("s.npy");
    npy_f64(&path, 3, 3, &m);
    let out = seasonloc(&[
        "solve",
        "--similarity",
        path.to_str().unwrap(),
        "--fan-out",
        "2",
    ])
    .success_json();
    let rows = out["hypotheses"][0]["rows"].as_array().unwrap();
    assert_eq!(rows[1]["matches"].as_array().unwrap().len(), 0, "{out}");
    assert_eq!(rows[2]["matches"][0]["ref"], 2);
}

#[test]
fn solve_with_two_flows_recovers_a_second_traversal() {
    let dir = Dir::new();
    // The query drives the reference route twice: rows 0..4 match 0..4 and rows 4..8 match 0..4
    // again. One forward-only path cannot take both; F = 2 can.
    let (q, d) = (8, 4);
    let mut m = vec![0.4f32; q * d];
    for i in 0..q {
        m[i * d + (i % 4)] = 2.5;
    }
    let path = dir.path("loop.npy");
    npy_f32(&path, q, d, &m);
    for exact in [false, true] {
        let mut args = vec![
            "solve",
            "--similarity",
            path.to_str().unwrap(),
            "--flows",
            "2",
            "--hidden-cost",
            "1.2",
        ];
        if exact {
            args.push("--exact");
        }
        let out = seasonloc(&args).success_json();
        let hyps = out["hypotheses"].as_array().unwrap();
        assert_eq!(hyps.len(), 2, "{out}");
        let matched: std::collections::BTreeSet<(i64, i64)> = hyps
            .iter()
            .flat_map(|h| h["rows"].as_array().unwrap().iter())
            .flat_map(|r| {
                let q = r["query"].as_i64().unwrap();
                r["matches"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(move |m| (q, m["ref"].as_i64().unwrap()))
            })
            .collect();
        for i in 0..8 {
            assert!(
                matched.contains(&(i, i % 4)),
                "exact={exact}: query {i} not matched to {}: {out}",
                i % 4
            );
        }
        let total: f64 = hyps.iter().map(|h| h["cost"].as_f64().unwrap()).sum();
        assert!((out["total_cost"].as_f64().unwrap() - total).abs() < 1e-9);
    }
}

#[test]
fn solve_rejects_bad_input_with_one_line() {
    let dir = Dir::new();
    let nan = dir.path("nan.npy");
    npy_f32(&nan, 2, 2, &[1.0, f32::NAN, 1.0, 1.0]);
    let garbage = dir.path("garbage.npy");
    std::fs::write(&garbage, b"hello").unwrap();
    let ok = dir.path("ok.npy");
    npy_f32(&ok, 1, 1, &[1.0]);
    let missing = dir.path("missing.npy");
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (
            vec!["solve", "--similarity", nan.to_str().unwrap()],
            "non-finite",
        ),
        (
            vec!["solve", "--similarity", garbage.to_str().unwrap()],
            "not a valid .npy",
        ),
        (
            vec!["solve", "--similarity", missing.to_str().unwrap()],
            "missing.npy",
        ),
        (
            vec![
                "solve",
                "--similarity",
                ok.to_str().unwrap(),
                "--flows",
                "0",
            ],
            "flows",
        ),
        (
            vec![
                "solve",
                "--similarity",
                ok.to_str().unwrap(),
                "--hidden-cost=-2",
            ],
            "hidden-cost",
        ),
        (
            vec![
                "solve",
                "--similarity",
                ok.to_str().unwrap(),
                "--stop-hidden-fraction",
                "2",
            ],
            "stop_hidden_fraction",
        ),
        // A missing argument is named, not only announced.
        (vec!["solve"], "--similarity"),
        // A negative value is the option's error, not an unknown argument `-1`.
        (
            vec![
                "solve",
                "--similarity",
                ok.to_str().unwrap(),
                "--fan-out",
                "-1",
            ],
            "--fan-out",
        ),
        (
            vec![
                "solve",
                "--similarity",
                ok.to_str().unwrap(),
                "--hidden-cost",
                "-1",
            ],
            "hidden-cost",
        ),
    ];
    for (args, needle) in cases {
        seasonloc(&args).failure_mentions(needle);
    }
}

/// `--similarity /dev/stdin`: a pipe is read as it comes (the size check of regular files
/// reads the header first and must not consume the stream), with the same answer as the file.
#[test]
fn solve_reads_a_matrix_piped_on_stdin() {
    let dir = Dir::new();
    let file = dir.path("m.npy");
    npy_f32(
        &file,
        3,
        4,
        &[3.0, 1.0, 1.0, 1.0, 1.0, 3.0, 1.0, 1.0, 1.0, 1.0, 3.0, 1.0],
    );
    let from_file = seasonloc(&["solve", "--similarity", file.to_str().unwrap()]).success_json();
    // A real pipe (a redirected file would reopen as a regular file).
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_seasonloc"))
        .args(["solve", "--similarity", "/dev/stdin"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let bytes = std::fs::read(&file).unwrap();
    let mut stdin = child.stdin.take().unwrap();
    std::io::Write::write_all(&mut stdin, &bytes).unwrap();
    drop(stdin);
    let piped = child.wait_with_output().unwrap();
    assert!(
        piped.status.success(),
        "{}",
        String::from_utf8_lossy(&piped.stderr)
    );
    let piped: Value = serde_json::from_slice(&piped.stdout).unwrap();
    assert_eq!(piped, from_file);
}
