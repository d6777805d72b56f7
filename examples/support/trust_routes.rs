//! The routes the outside trust check (`check_trust.py`) drives, for any region of a Nordland-like
//! folder, and the Gardens Point pairings it drives: shared by the trust harness
//! (`examples/trust_features.rs`) and the calibration (`examples/calibrate.rs`).
//!
//! Nordland (`summer/` = map, `winter/` = query, frame `i` of each = the same place): the map is
//! summer frames `start .. start + len` (`len` = 1000 in the check), routes are lists of offsets
//! from `start`, an offset `>= len` is off the map (offsets up to `len + 175` are used).

#![allow(dead_code)] // each includer uses a different part

use std::path::{Path, PathBuf};

use seasonloc_core::features::hog::{HogOptions, HogSpec};
use seasonloc_core::features::{extract_files, image_file_size, Fit, Fitted};
use seasonloc_core::similarity::cosine_matrix;
use seasonloc_core::trip::{column_prior, FrameEstimate, FrameEvidence, Trip, TripParams};
use seasonloc_core::Matrix;

/// One derived drive: its name and the pool frames it shows, in driving order, with the true
/// map place of each (`None`: off the map).
pub struct Route {
    pub name: String,
    pub frames: Vec<usize>,
    pub truth: Vec<Option<usize>>,
}

/// A map and the query pool a set of routes is drawn from.
pub struct Region {
    pub name: String,
    /// Map descriptors, one row per place.
    pub map: Matrix,
    /// Query descriptors, one row per pool frame.
    pub pool: Matrix,
    pub tolerance: usize,
    pub routes: Vec<Route>,
}

/// Image files of a folder with one of the given extensions, sorted by name.
pub fn files(dir: &Path, ext: &str) -> Vec<PathBuf> {
    let mut f: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.expect("readable folder").path())
        .filter(|p| p.extension().is_some_and(|e| e == ext))
        .collect();
    f.sort();
    f
}

/// The check's five Nordland drives as offsets from the map's first frame, for a map of `len`
/// places (the check: 1000).
pub fn nordland_orders(len: usize) -> Vec<(&'static str, Vec<usize>)> {
    // The check's fractions of its 1000-frame map, kept for other lengths.
    let at = |x: usize| x * len / 1000;
    let speed: Vec<usize> = (0..at(400))
        .step_by(2)
        .chain((at(400)..at(700)).step_by(3))
        .chain((at(700)..at(900)).flat_map(|f| [f, f]))
        .chain(at(900)..len)
        .collect();
    vec![
        ("straight", (0..len).collect()),
        ("speed", speed),
        (
            "loop",
            (0..at(600))
                .chain(at(200)..at(600))
                .chain(at(600)..at(900))
                .collect(),
        ),
        (
            "detour",
            (0..at(400))
                .chain(len..len + 60)
                .chain(at(460)..len)
                .collect(),
        ),
        ("off_end", (at(700)..len).chain(len..len + 176).collect()),
    ]
}

/// A Nordland region: map summer `start .. start + len` (HOG 8 px, as the check), pool winter
/// `start .. start + len + 176`, the check's routes, tolerance 1.
pub fn nordland(dir: &Path, start: usize, len: usize) -> Region {
    let spec = HogSpec::new(HogOptions {
        cell_size: 8,
        resize: None,
    })
    .expect("valid HOG");
    let summer = files(&dir.join("summer"), "png");
    let winter = files(&dir.join("winter"), "png");
    let end = start + len + 176;
    assert!(
        end <= winter.len(),
        "region {start}+{len} needs winter frames up to {end}, the folder has {}",
        winter.len()
    );
    let map = extract_files(&spec, &summer[start..start + len], &|| {}).expect("summer");
    let pool = extract_files(&spec, &winter[start..end], &|| {}).expect("winter");
    let routes = nordland_orders(len)
        .into_iter()
        .map(|(name, frames)| Route {
            name: name.to_string(),
            truth: frames.iter().map(|&f| (f < len).then_some(f)).collect(),
            frames,
        })
        .collect();
    Region {
        name: format!("nordland_{start}_{len}"),
        map,
        pool,
        tolerance: 1,
        routes,
    }
}

/// Gardens Point: night_right frames 0..99 against the `reference` walk (`day_right` or
/// `day_left`), HOG with the default 32 px cells at the map's geometry (night frames
/// stretched to it), tolerance 2.
pub fn gardens_point(dir: &Path, reference: &str) -> Region {
    let day = files(&dir.join(reference), "jpg");
    let night = files(&dir.join("night_right"), "jpg");
    let geometry = image_file_size(&day[0]).expect("readable image");
    let hog = Fitted::hog(32, geometry, Fit::Stretch).expect("valid HOG");
    let map = extract_files(&hog, &day, &|| {}).expect("day");
    let pool = extract_files(&hog, &night, &|| {}).expect("night");
    let n = night.len().min(day.len());
    Region {
        name: format!("gp_night_on_{reference}"),
        map,
        pool,
        tolerance: 2,
        routes: vec![Route {
            name: "night".into(),
            frames: (0..n).collect(),
            truth: (0..n).map(Some).collect(),
        }],
    }
}

impl Region {
    /// The query descriptors of a route.
    pub fn queries(&self, route: &Route) -> Matrix {
        let rows: Vec<&[f32]> = route.frames.iter().map(|&f| self.pool.row(f)).collect();
        Matrix::from_rows(&rows).expect("rows")
    }
}

/// One frame's answer as reported at some batch, with its evidence.
#[derive(Clone, Copy)]
pub struct Seen {
    pub estimate: FrameEstimate,
    pub evidence: Option<FrameEvidence>,
}

/// Streams a route through a trip with `params` in batches of 10 (as `check_trust.py`) and returns, per frame, the answer at
/// arrival, the final one, and how often its reference moved between re-traces.
pub fn drive(region: &Region, route: &Route, params: TripParams) -> Vec<(Seen, Seen, usize)> {
    let q = region.queries(route);
    let c = cosine_matrix(&q, &region.map).expect("cosine");
    let prior = column_prior(&region.map).expect("prior");
    let mut trip = Trip::new(prior, params).expect("valid parameters");
    let n = c.rows();
    let mut arrival: Vec<Option<Seen>> = vec![None; n];
    let mut last: Vec<Option<Seen>> = vec![None; n];
    let mut changes = vec![0usize; n];
    let tol = region.tolerance;
    for start in (0..n).step_by(10) {
        let end = (start + 10).min(n);
        let rows: Vec<&[f32]> = (start..end).map(|i| c.row(i)).collect();
        let u = trip
            .push_batch(&Matrix::from_rows(&rows).expect("rows"))
            .expect("batch");
        let ev = |f: usize| trip.last_evidence().iter().find(|e| e.frame == f).copied();
        for e in &u.estimates {
            arrival[e.frame] = Some(Seen {
                estimate: *e,
                evidence: ev(e.frame),
            });
        }
        for e in u.estimates.iter().chain(&u.window) {
            let seen = Seen {
                estimate: *e,
                evidence: ev(e.frame),
            };
            if let Some(prev) = last[e.frame] {
                let moved = match (prev.estimate.reference, e.reference) {
                    (Some(a), Some(b)) => a.abs_diff(b) > tol,
                    (None, None) => false,
                    _ => true,
                };
                changes[e.frame] += usize::from(moved);
            }
            last[e.frame] = Some(seen);
        }
    }
    (0..n)
        .map(|i| {
            (
                arrival[i].expect("every frame arrives"),
                last[i].expect("every frame is reported"),
                changes[i],
            )
        })
        .collect()
}
