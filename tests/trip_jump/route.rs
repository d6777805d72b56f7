//! The derived jump route of the relocalization check and how its delays are measured: a
//! Nordland-specific harness, so it lives with the tests (`tests/trip_jump/main.rs`) and
//! `examples/trip_nordland.rs` includes it, not in the library.

#![allow(dead_code)] // each includer uses a different part

use seasonloc_core::trip::FrameEstimate;

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
/// ([`FrameEstimate::is_lost`]). `None` when that never happens.
pub fn relocalization_delays(route: &JumpRoute, estimates: &[FrameEstimate]) -> Vec<Option<usize>> {
    route
        .segments
        .iter()
        .map(|&(first, a, b)| {
            let ok = |t: usize| -> bool {
                let truth = route.frames[t];
                let e = &estimates[t];
                if truth >= route.map_len {
                    e.is_lost()
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
