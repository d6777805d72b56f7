//! Helpers that make the CLI tests read like prose: temporary folders, `.npy` writers, a
//! generated image route, and a runner for the `seasonloc` binary.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use serde_json::Value;

/// A temporary folder that is removed when dropped.
pub struct Dir(tempfile::TempDir);

impl Dir {
    pub fn new() -> Self {
        Dir(tempfile::tempdir().expect("temporary folder"))
    }

    pub fn path(&self, rel: &str) -> PathBuf {
        self.0.path().join(rel)
    }
}

/// `rel` of the public data (`data/<dataset>/...`, `models/...`) where the tests find it
/// (`seasonloc_test_support::datasets`), or `None` (with a message) when it is absent.
pub fn shared(rel: &str) -> Option<PathBuf> {
    seasonloc_test_support::datasets::resolve(rel)
}

/// The result of one `seasonloc` run.
pub struct Run {
    args: Vec<String>,
    pub output: Output,
}

/// Runs the built `seasonloc` binary.
pub fn seasonloc(args: &[&str]) -> Run {
    let output = Command::new(env!("CARGO_BIN_EXE_seasonloc"))
        .args(args)
        .output()
        .expect("run seasonloc");
    Run {
        args: args.iter().map(|s| s.to_string()).collect(),
        output,
    }
}

impl Run {
    /// Asserts success and parses stdout as one JSON document.
    pub fn success_json(&self) -> Value {
        assert!(
            self.output.status.success(),
            "seasonloc {:?} failed: {}",
            self.args,
            String::from_utf8_lossy(&self.output.stderr)
        );
        serde_json::from_slice(&self.output.stdout).expect("stdout is JSON")
    }

    /// Asserts failure with a one-line message on stderr that mentions `needle`.
    pub fn failure_mentions(&self, needle: &str) {
        let stderr = String::from_utf8_lossy(&self.output.stderr);
        assert!(
            !self.output.status.success(),
            "seasonloc {:?} should fail",
            self.args
        );
        assert!(
            self.output.stdout.is_empty(),
            "nothing on stdout on failure: {:?}",
            self.args
        );
        assert!(
            stderr.contains(needle),
            "seasonloc {:?}: `{needle}` not in: {stderr}",
            self.args
        );
        assert_eq!(stderr.trim_end().lines().count(), 1, "one line: {stderr}");
        // An error and its source both in the line ("x: No such file: No such file") reads
        // as two failures.
        let clauses: Vec<&str> = stderr.trim_end().split(": ").collect();
        assert!(
            clauses.windows(2).all(|w| w[0] != w[1]),
            "a clause repeated: {stderr}"
        );
    }
}

fn npy(path: &Path, descr: &str, rows: usize, cols: usize, body: &[u8]) {
    let mut header =
        format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': ({rows}, {cols}), }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    bytes.extend_from_slice(body);
    std::fs::write(path, bytes).expect("write .npy");
}

/// Writes a float32 `.npy` matrix.
pub fn npy_f32(path: &Path, rows: usize, cols: usize, data: &[f32]) {
    let body: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
    npy(path, "<f4", rows, cols, &body);
}

/// Writes a float64 `.npy` matrix.
pub fn npy_f64(path: &Path, rows: usize, cols: usize, data: &[f64]) {
    let body: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
    npy(path, "<f8", rows, cols, &body);
}

/// Folders and ground truth of a generated route.
pub struct Route {
    pub reference: String,
    pub query: String,
    pub ground_truth: String,
}

/// A tiny deterministic generator (xorshift) so tests need no RNG crate.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// A generated route: `refs` 64x32 "places" (random rectangles on a gradient), and `queries`
/// frames that revisit places `0..queries` in order under another "season" (darker, inverted
/// contrast in one channel, noise). Ground truth: query i -> reference i.
pub fn write_route(dir: &Dir, refs: usize, queries: usize) -> Route {
    let reference = dir.path("reference");
    let query = dir.path("query");
    std::fs::create_dir_all(&reference).unwrap();
    std::fs::create_dir_all(&query).unwrap();
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    let mut gt = String::from("query_index,ref_index\n");
    for p in 0..refs {
        let mut img = image::RgbImage::from_fn(64, 32, |x, y| {
            let v = (x * 2 + y) as u8;
            image::Rgb([v, v, v])
        });
        for _ in 0..6 {
            let (x0, y0) = (rng.below(56) as u32, rng.below(24) as u32);
            let (w, h) = (4 + rng.below(16) as u32, 4 + rng.below(10) as u32);
            let shade = rng.below(256) as u8;
            for y in y0..(y0 + h).min(32) {
                for x in x0..(x0 + w).min(64) {
                    img.put_pixel(x, y, image::Rgb([shade, shade, shade]));
                }
            }
        }
        img.save(reference.join(format!("frame-{p:05}.png")))
            .unwrap();
        if p < queries {
            let mut winter = img.clone();
            for px in winter.pixels_mut() {
                let n = rng.below(21) as i32 - 10;
                let v = ((i32::from(px[0]) * 3 / 5) + 40 + n).clamp(0, 255) as u8;
                *px = image::Rgb([v, v, v]);
            }
            winter
                .save(query.join(format!("frame-{p:05}.png")))
                .unwrap();
            gt.push_str(&format!("{p},{p}\n"));
        }
    }
    let ground_truth = dir.path("gt.csv");
    std::fs::write(&ground_truth, gt).unwrap();
    Route {
        reference: reference.to_str().unwrap().into(),
        query: query.to_str().unwrap().into(),
        ground_truth: ground_truth.to_str().unwrap().into(),
    }
}
