//! The relocalization check on the derived Nordland jump route (README, `docs/parameters.md`):
//! streams real winter frames through a [`Trip`] and measures how many frames each jump takes
//! to relocalize. Skips with a message when the shared data is absent.

#[path = "../support/nordland.rs"]
mod nordland;
mod route;
#[path = "../../examples/support/trip_stream.rs"]
mod trip_stream;

use route::{jump_route, relocalization_delays, JumpRoute};
use seasonloc_core::similarity;
use seasonloc_core::trip::{column_prior, TripParams};
use seasonloc_core::Matrix;
use trip_stream::stream;

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
        let (arrival, _) = stream(&c, &prior, params, 10);
        let delays = relocalization_delays(&route, &arrival);
        let (a, b) = (route.segments[2].0, route.segments[3].0);
        let lost = arrival[a..b].iter().filter(|e| e.is_lost()).count();
        eprintln!(
            "R {r}: delays {delays:?}, off-map frames reported lost {lost}/{}",
            b - a
        );
    }
}

fn nordland_jump_inputs() -> Option<(Matrix, Matrix, JumpRoute)> {
    use seasonloc_core::features::extract_files;
    use seasonloc_core::features::hog::{HogOptions, HogSpec};
    let dir = nordland::nordland()?;
    let files = |season: &str| nordland::nordland_files(&dir.join(season));
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
    let (arrival, _) = stream(&c, &prior, TripParams::default(), 10);
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
