//! The derived jump route of the relocalization check and how its delays are measured (used by
//! the tests below on real data and by `examples/trip_nordland.rs`).

use super::{FrameEstimate, LOST_RATIO};

/// The derived route of the relocalization check (README, `docs/parameters.md`): the map is
/// summer frames `0..map_len`; the vehicle drives winter frames 1200-1499, jumps back to
/// 300-599, then drives 2100-2249, a part of the line that is *not on the map*, and re-enters
/// the map at 800-999 (not 700: winter 708-738 is matched 2-14 frames off even by the offline
/// solve of the whole sequence, so a re-entry there would measure the data). Winter frame `i`
/// shows the place of summer frame `i`.
#[derive(Clone, Debug, PartialEq)]
pub struct JumpRoute {
    /// Map size: summer frames `0..map_len`.
    pub map_len: usize,
    /// The winter frame index of each trip frame, in driving order.
    pub frames: Vec<usize>,
    /// `(first trip frame, first winter frame, end winter frame)` of each straight segment.
    pub segments: Vec<(usize, usize, usize)>,
}

/// The route described on [`JumpRoute`].
pub fn jump_route() -> JumpRoute {
    let map_len = 2000;
    let mut frames = Vec::new();
    let mut segments = Vec::new();
    for (a, b) in [(1200, 1500), (300, 600), (2100, 2250), (800, 1000)] {
        segments.push((frames.len(), a, b));
        frames.extend(a..b);
    }
    JumpRoute {
        map_len,
        frames,
        segments,
    }
}

/// Consecutive frames that must agree before a segment counts as found.
pub const FOUND_RUN: usize = 10;

/// For each segment of `route`, the frames from its start until the per-frame estimates
/// (`estimates[t]` for trip frame `t`) settle: on the map, the first offset from which
/// [`FOUND_RUN`] consecutive frames are within ±1 frame of the true place; off the map, the
/// first offset from which [`FOUND_RUN`] consecutive frames are reported as not on the map
/// (no reference, or confidence at most [`LOST_RATIO`]). `None` when that never happens.
pub fn relocalization_delays(route: &JumpRoute, estimates: &[FrameEstimate]) -> Vec<Option<usize>> {
    route
        .segments
        .iter()
        .map(|&(first, a, b)| {
            let ok = |t: usize| -> bool {
                let truth = route.frames[t];
                let e = &estimates[t];
                if truth >= route.map_len {
                    e.reference.is_none() || e.confidence <= LOST_RATIO
                } else {
                    e.reference.is_some_and(|j| j.abs_diff(truth) <= 1)
                }
            };
            let len = b - a;
            (0..len.saturating_sub(FOUND_RUN - 1))
                .find(|&k| (first + k..first + k + FOUND_RUN).all(ok))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::similarity;
    use crate::trip::{column_prior, Trip, TripParams};
    use crate::Matrix;

    /// Prints the jump route's delays and the dev-split AP for a grid of `R` (tuning aid).
    #[test]
    #[ignore = "reads the shared Nordland data; prints measurements"]
    fn nordland_relocalization_cost_grid() {
        let Some((summer, winter, route)) = nordland_jump_inputs() else {
            return;
        };
        let c = similarity::cosine_matrix(&winter, &summer).unwrap();
        let prior = column_prior(&summer).unwrap();
        for r in [0.25, 0.5, 1.0, 1.5, 2.0] {
            let params = TripParams {
                relocalization: Some(r),
                ..TripParams::default()
            };
            let arrival = stream(&c, &prior, params);
            let delays = relocalization_delays(&route, &arrival);
            let (a, b) = (route.segments[2].0, route.segments[3].0);
            let lost = arrival[a..b]
                .iter()
                .filter(|e| e.reference.is_none() || e.confidence <= LOST_RATIO)
                .count();
            eprintln!(
                "R {r}: delays {delays:?}, off-map frames reported lost {lost}/{}",
                b - a
            );
        }
    }

    fn stream(c: &Matrix, prior: &[f32], params: TripParams) -> Vec<FrameEstimate> {
        let mut trip = Trip::new(prior.to_vec(), params).unwrap();
        let mut arrival = Vec::new();
        for start in (0..c.rows()).step_by(10) {
            let rows: Vec<&[f32]> = (start..(start + 10).min(c.rows()))
                .map(|i| c.row(i))
                .collect();
            arrival.extend(
                trip.push_batch(&Matrix::from_rows(&rows).unwrap())
                    .unwrap()
                    .estimates,
            );
        }
        arrival
    }

    fn nordland_jump_inputs() -> Option<(Matrix, Matrix, JumpRoute)> {
        use crate::features::extract_files;
        use crate::features::hog::{HogOptions, HogSpec};
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let Some(dir) = ["../shared", "../../shared"]
            .iter()
            .map(|s| root.join(s).join("data/nordland_64x32"))
            .find(|d| d.join("summer").is_dir())
        else {
            eprintln!("SKIPPED: ../shared/data/nordland_64x32 not found");
            return None;
        };
        let files = |season: &str| -> Vec<std::path::PathBuf> {
            let mut f: Vec<_> = std::fs::read_dir(dir.join(season))
                .unwrap()
                .map(|e| e.unwrap().path())
                .filter(|p| p.extension().is_some_and(|e| e == "png"))
                .collect();
            f.sort();
            f
        };
        let route = jump_route();
        let spec = HogSpec::new(HogOptions {
            cell_size: 8,
            resize: None,
        })
        .unwrap();
        let summer = extract_files(&spec, &files("summer")[..route.map_len], &|| {}).unwrap();
        let winter_files = files("winter");
        let picked: Vec<_> = route
            .frames
            .iter()
            .map(|&i| winter_files[i].clone())
            .collect();
        let winter = extract_files(&spec, &picked, &|| {}).unwrap();
        Some((summer, winter, route))
    }

    /// The derived jump route on real data: every jump is relocalized within 15 frames with
    /// the shipped defaults (skips with a message when the shared data is absent).
    #[test]
    fn nordland_jump_route_is_relocalized_within_15_frames() {
        let Some((summer, winter, route)) = nordland_jump_inputs() else {
            return;
        };
        let c = similarity::cosine_matrix(&winter, &summer).unwrap();
        let prior = column_prior(&summer).unwrap();
        let arrival = stream(&c, &prior, TripParams::default());
        let delays = relocalization_delays(&route, &arrival);
        eprintln!("relocalization delays per segment: {delays:?}");
        // The start, the jump back (1499 -> 300), the stretch off the map and the re-entry
        // after it are each found within 15 frames.
        for (seg, d) in route.segments.iter().zip(&delays) {
            assert!(
                d.is_some_and(|d| d <= 15),
                "segment {seg:?}: {d:?} ({delays:?})"
            );
        }
    }
}
