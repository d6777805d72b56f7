//! Trust: a calibrated probability `p_correct` that an estimate's reference is within the
//! tolerance of the true place, and the statuses a fleet acts on.
//!
//! The raw `confidence` (the discounted min-marginal ratio, [`crate::confidence`]) ranks
//! estimates well but means different things on different routes: it lives between about 0.98
//! and 1.04, and on the dev data the same value is right 20 % of the time on one part of the
//! route and 60 % on another. `p_correct` is a *calibrated* reading of the evidence the method
//! already has: among estimates with `p_correct` near `x`, a fraction `x` is right.
//!
//! **Trips** ([`trip_p_correct`]): a logistic model on [`trip_features`] of the trip's
//! [`FrameEvidence`]: the ratio (log, with two hinges, as the relation bends at 1), how long
//! the path has parked on the reference (`dwell`: a path that stands still while the vehicle
//! moves is the typical wrong estimate), the look-ahead behind the estimate (frames after it in
//! the lag window; none for the newest), frames since the path's last relocalization jump, the
//! regularity of the path's recent advance, the map's prior at the match (a place unlike the
//! rest of the map has its `ĉ` lifted by Eq. 2: dark tunnel frames) and the tolerance (the
//! model gives `P(|error| <= tol)`; fitted on tolerances 1 and 2).
//!
//! **Offline** ([`offline_p_correct`]): the same kind of model on [`offline_features`] of a
//! prediction's [`PredictionEvidence`]: the ratio, the rank of the hypothesis that gave it
//! (a further flow's prediction is a second visit the first route could not make), the
//! contrast of the match in its row and along its stretch, the regularity of the predictions'
//! advance, how long the predictions park on the reference (`dwell`, as for trips), the
//! tolerance.
//!
//! **Fit** (`examples/calibrate.rs`, which writes `calibration/fitted.rs`): on Nordland dev
//! routes derived as `check_trust.py` derives them, built from frames 1200-2399 (map summer
//! 1200-2199); checked on frames 17-1192 and on Gardens Point, which the fit never sees.
//! Measured results and the second design compared: ARCHITECTURE.md ("Trust").
//!
//! **Statuses** ([`FrameStatus`], [`frame_status`]): `localized` when `p_correct` reaches
//! the threshold (0.9 by default); otherwise `lost` while the evidence is not there yet (the
//! trip's first `L` frames) or the path is relocalizing (a jump within the last `L` frames),
//! else `uncertain` with a reference and `off_map` without one.

pub mod fit;
mod fitted;
pub mod offline;

pub use offline::{
    prediction_evidence, relative_column_means, PredictionEvidence, RankedPrediction,
};

/// The default `p_correct` at which an estimate is `localized`.
pub const DEFAULT_THRESHOLD: f64 = 0.9;

/// The evidence behind one trip frame's estimate, after a batch (computed by the trip from its
/// lag window, `crate::trip::evidence`; read by [`trip_p_correct`] and [`frame_status`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameEvidence {
    /// Frame index since the trip started.
    pub frame: usize,
    /// The path's match before the stretch rule (`None`: the path hides the frame).
    pub path_reference: Option<usize>,
    /// The discounted min-marginal ratio at the path's match (0 when hidden): `outside / inside`.
    pub ratio: f64,
    /// The cheapest route hidden at the frame over the cheapest through the match's band,
    /// `H / inside` (the stake rule's ingredients; `+inf` when no route is hidden there).
    pub hidden_ratio: f64,
    /// The hidden cost `W` minus the cost `1/ĉ` of the band's best node: what the image
    /// contributes against "off the map" (negative: a node dearer than hiding).
    pub stake: f64,
    /// Robust `z` of the match in its `ĉ` row (0 when hidden).
    pub contrast: f64,
    /// Mean contrast of the last `L` matched frames of the path ending at this one (the
    /// stretch rule's causal statistic); `NaN` with fewer than `L` matched frames so far in
    /// the window.
    pub stretch_trailing: f64,
    /// Least mean contrast over the stretches of `L` matched frames that hold this one (what
    /// the stretch rule compares with its bar); `NaN` when none.
    pub stretch_min: f64,
    /// The stretch rule put the frame off the map.
    pub marked: bool,
    /// Frames after this one in the window (the look-ahead its estimate rests on).
    pub later: usize,
    /// Frames since the path last entered a row by a relocalization jump, at or before this
    /// one (0: this row; the window's length when no jump lies in the window).
    pub since_jump: usize,
    /// Rows the path hides among the `L` rows ending at this one.
    pub hidden_trailing: usize,
    /// Mean advance of the path in references per frame over its last `L` matched frames
    /// ending here (`NaN` with fewer than 2).
    pub step_mean: f64,
    /// Mean absolute deviation of those advances from their median (path regularity).
    pub step_spread: f64,
    /// `ĉ` of the match (0 when hidden).
    pub chat: f64,
    /// `ĉ` of the match over the row's largest `ĉ`.
    pub chat_of_best: f64,
    /// Distance in references from the match to the row's largest `ĉ`.
    pub best_offset: usize,
    /// The map's prior column mean at the match over the prior's median (how much the place
    /// looks like the rest of the map; 0 when hidden).
    pub prior: f64,
    /// The hidden cost `W` of the trip.
    pub hidden_cost: f64,
    /// Mean contrast of the `L` matched frames of the window nearest this one (centred where
    /// the window allows; fewer when the window holds fewer).
    pub stretch_local: f64,
    /// Largest ratio of the `L` matched frames before this one in the window (`NaN`: none).
    pub ratio_before: f64,
    /// Largest ratio of the `L` matched frames after this one in the window (`NaN`: none).
    pub ratio_after: f64,
    /// Mean log ratio of the `L` matched frames of the window nearest this one.
    pub log_ratio_local: f64,
    /// Frames up to this one, in a row, that the path matches at this reference (parking).
    pub dwell: usize,
    /// The `ĉ` row's robust standard deviation (`NaN` without a spread).
    pub row_scale: f64,
    /// The `ĉ` row's median (`NaN` without a spread).
    pub row_median: f64,
}

/// What an estimate means for a vehicle.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameStatus {
    /// A reference with `p_correct` at or above the threshold: act on it.
    Localized,
    /// A reference is given, but `p_correct` is below the threshold: not to be acted on.
    Uncertain,
    /// No reference: the evidence says the vehicle is not on the mapped route.
    OffMap,
    /// Not enough evidence yet (the trip's first frames) or the path is relocalizing.
    Lost,
}

impl FrameStatus {
    /// Every status, in the order of their [`FrameStatus::code`]s.
    pub const ALL: [FrameStatus; 4] = [
        FrameStatus::Localized,
        FrameStatus::Uncertain,
        FrameStatus::OffMap,
        FrameStatus::Lost,
    ];

    /// The stable number the stores and stored replies keep for a status (1-4).
    pub fn code(self) -> u8 {
        match self {
            FrameStatus::Localized => 1,
            FrameStatus::Uncertain => 2,
            FrameStatus::OffMap => 3,
            FrameStatus::Lost => 4,
        }
    }

    /// The status of a stored [`FrameStatus::code`], `None` for an unknown number.
    pub fn from_code(code: u8) -> Option<FrameStatus> {
        FrameStatus::ALL.into_iter().find(|s| s.code() == code)
    }

    /// The status of an estimate stored before `p_correct` existed: `off_map` without a
    /// reference, else `uncertain` (with `p_correct` 0: nothing calibrated says to act on it).
    pub fn before_calibration(reference: Option<usize>) -> FrameStatus {
        if reference.is_some() {
            FrameStatus::Uncertain
        } else {
            FrameStatus::OffMap
        }
    }

    /// The status's name on the wire: `localized`, `uncertain`, `off_map`, `lost`.
    pub fn as_str(self) -> &'static str {
        match self {
            FrameStatus::Localized => "localized",
            FrameStatus::Uncertain => "uncertain",
            FrameStatus::OffMap => "off_map",
            FrameStatus::Lost => "lost",
        }
    }
}

/// The status of a frame estimate with `reference` and `p_correct`, given its evidence: see
/// the module doc. `settle` is the number of frames the evidence needs after the trip's start
/// or a relocalization jump (the stretch length `L`).
pub fn frame_status(
    reference: Option<usize>,
    p_correct: f64,
    evidence: &FrameEvidence,
    threshold: f64,
    settle: usize,
) -> FrameStatus {
    if reference.is_some() && p_correct >= threshold {
        return FrameStatus::Localized;
    }
    if evidence.frame < settle || evidence.since_jump < settle {
        return FrameStatus::Lost;
    }
    match reference {
        Some(_) => FrameStatus::Uncertain,
        None => FrameStatus::OffMap,
    }
}

/// `100 · ln(ratio)` clamped to `[-3, 5]` (a ratio of 0, no local route through the match,
/// is -3): the ratio in percent, where its information lies.
fn log_ratio(ratio: f64) -> f64 {
    if ratio > 0.0 {
        (100.0 * ratio.ln()).clamp(-3.0, 5.0)
    } else {
        -3.0
    }
}

/// `ln(tolerance)` (a tolerance of 0 counts as 1: the frame itself).
fn log_tolerance(tolerance: usize) -> f64 {
    (tolerance.max(1) as f64).ln()
}

/// Number of [`trip_features`].
pub const TRIP_FEATURES: usize = 10;

/// Names of [`trip_features`], in order.
pub const TRIP_FEATURE_NAMES: [&str; TRIP_FEATURES] = [
    "log_ratio_below_0",
    "log_ratio_0_to_2",
    "log_ratio_above_2",
    "log_dwell",
    "look_ahead",
    "newest",
    "since_jump",
    "step_spread",
    "log_prior",
    "log_tolerance",
];

/// The three segments of the log ratio `l` ([`log_ratio`]): `min(l, 0)`, `l` clamped to
/// `[0, 2]` and `max(l - 2, 0)`. Their coefficients are the slopes of `p`'s logit on each
/// segment; the fit keeps them `>= 0` (`examples/calibrate.rs`), so `p_correct` never falls
/// as the ratio rises.
fn ratio_segments(ratio: f64) -> [f64; 3] {
    let l = log_ratio(ratio);
    [l.min(0.0), l.clamp(0.0, 2.0), (l - 2.0).max(0.0)]
}

/// Indices of the ratio segments in both feature vectors (whose slopes the fit keeps `>= 0`).
pub const RATIO_SEGMENTS: [usize; 3] = [0, 1, 2];

/// The features the trip model reads from a frame's evidence (names: [`TRIP_FEATURE_NAMES`]):
/// the ratio's three segments (`ratio_segments`), `ln(dwell)`,
/// `min(later, 31) / 31`, `later == 0`, `min(since_jump, 32) / 32`, the step spread clamped to
/// `[0, 5]` (2 when unknown), `ln(prior)` clamped to `[-2, 1]` (the prior floored at 0.05) and
/// `ln(tolerance)`.
pub fn trip_features(ev: &FrameEvidence, tolerance: usize) -> [f64; TRIP_FEATURES] {
    let [a, b, c] = ratio_segments(ev.ratio);
    let spread = if ev.step_spread.is_nan() {
        2.0
    } else {
        ev.step_spread.clamp(0.0, 5.0)
    };
    [
        a,
        b,
        c,
        (ev.dwell.max(1) as f64).ln(),
        ev.later.min(31) as f64 / 31.0,
        f64::from(u8::from(ev.later == 0)),
        ev.since_jump.min(32) as f64 / 32.0,
        spread,
        ev.prior.max(0.05).ln().clamp(-2.0, 1.0),
        log_tolerance(tolerance),
    ]
}

/// `p_correct` of a trip frame whose estimate names a reference, from its evidence (0 for a
/// frame the path does not match).
pub fn trip_p_correct(ev: &FrameEvidence, tolerance: usize) -> f64 {
    if ev.path_reference.is_none() {
        return 0.0;
    }
    fit::sigmoid(fit::linear(
        &fitted::TRIP_COEFFICIENTS,
        &trip_features(ev, tolerance),
    ))
}

/// Number of [`offline_features`].
pub const OFFLINE_FEATURES: usize = 10;

/// Names of [`offline_features`], in order.
pub const OFFLINE_FEATURE_NAMES: [&str; OFFLINE_FEATURES] = [
    "log_ratio_below_0",
    "log_ratio_0_to_2",
    "log_ratio_above_2",
    "further_flow",
    "contrast",
    "stretch_centered",
    "stretch_min",
    "step_spread",
    "log_dwell",
    "log_tolerance",
];

/// The features the offline model reads from a prediction's evidence (names:
/// [`OFFLINE_FEATURE_NAMES`]): the ratio's segments as for trips, whether a further
/// flow (rank > 0) gave it, the contrast clamped to `[-3, 10]`, the centred and the least
/// stretch mean clamped to `[-3, 8]` (the least falls back to the centred one), the step
/// spread clamped to `[0, 5]` (2 when unknown), `ln(dwell)` and `ln(tolerance)`.
pub fn offline_features(ev: &PredictionEvidence, tolerance: usize) -> [f64; OFFLINE_FEATURES] {
    let [a, b, c] = ratio_segments(ev.ratio);
    let or = |x: f64, y: f64| if x.is_nan() { y } else { x };
    let centred = or(ev.stretch_centered, 0.0).clamp(-3.0, 8.0);
    [
        a,
        b,
        c,
        f64::from(u8::from(ev.rank > 0)),
        or(ev.contrast, 0.0).clamp(-3.0, 10.0),
        centred,
        or(ev.stretch_min, centred).clamp(-3.0, 8.0),
        or(ev.step_spread, 2.0).clamp(0.0, 5.0),
        (ev.dwell.max(1) as f64).ln(),
        log_tolerance(tolerance),
    ]
}

/// `p_correct` of an offline prediction from its evidence.
pub fn offline_p_correct(ev: &PredictionEvidence, tolerance: usize) -> f64 {
    fit::sigmoid(fit::linear(
        &fitted::OFFLINE_COEFFICIENTS,
        &offline_features(ev, tolerance),
    ))
}

/// The shipped coefficients (intercept first), for reports.
pub fn shipped() -> (&'static [f64], &'static [f64]) {
    (&fitted::TRIP_COEFFICIENTS, &fitted::OFFLINE_COEFFICIENTS)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame's evidence: a matched frame in the middle of a trip, some defaults.
    fn evidence(ratio: f64) -> FrameEvidence {
        FrameEvidence {
            frame: 100,
            path_reference: Some(40),
            ratio,
            hidden_ratio: 1.02,
            stake: 0.3,
            contrast: 3.0,
            stretch_trailing: 3.0,
            stretch_min: 3.0,
            marked: false,
            later: 5,
            since_jump: 32,
            hidden_trailing: 0,
            step_mean: 1.0,
            step_spread: 0.2,
            chat: 1.2,
            chat_of_best: 1.0,
            best_offset: 0,
            prior: 1.0,
            hidden_cost: 1.2,
            stretch_local: 3.0,
            ratio_before: 1.01,
            ratio_after: 1.01,
            log_ratio_local: 0.01,
            dwell: 1,
            row_scale: 0.1,
            row_median: 1.0,
        }
    }

    fn prediction(ratio: f64) -> PredictionEvidence {
        PredictionEvidence {
            query: 10,
            reference: 12,
            rank: 0,
            ratio,
            contrast: 3.0,
            stretch_centered: 3.0,
            stretch_min: 2.5,
            step_mean: 1.0,
            step_spread: 0.2,
            chat: 1.2,
            chat_of_best: 1.0,
            best_offset: 0,
            stake: 0.3,
            hidden_ratio: 1.02,
            column: 1.0,
            dwell: 1,
        }
    }

    #[test]
    fn p_correct_never_falls_as_the_ratio_rises_and_grows_with_the_tolerance() {
        let ratios: Vec<f64> = (0..=200).map(|k| 0.95 + f64::from(k) * 0.0005).collect();
        for tol in [1, 2, 5] {
            let trip: Vec<f64> = ratios
                .iter()
                .map(|&r| trip_p_correct(&evidence(r), tol))
                .collect();
            let offline: Vec<f64> = ratios
                .iter()
                .map(|&r| offline_p_correct(&prediction(r), tol))
                .collect();
            for p in [&trip, &offline] {
                assert!(p.windows(2).all(|w| w[1] >= w[0]), "{p:?}");
                assert!(p.iter().all(|&p| (0.0..=1.0).contains(&p)));
            }
        }
        for &r in &ratios {
            assert!(trip_p_correct(&evidence(r), 2) >= trip_p_correct(&evidence(r), 1));
            assert!(offline_p_correct(&prediction(r), 2) >= offline_p_correct(&prediction(r), 1));
        }
        // A frame the path hides has no reference to be right about.
        let hidden = FrameEvidence {
            path_reference: None,
            ..evidence(1.05)
        };
        assert_eq!(trip_p_correct(&hidden, 1), 0.0);
    }

    #[test]
    fn features_are_clamped_and_unknowns_have_fixed_values() {
        let f = trip_features(&evidence(1.01), 1);
        assert_eq!(f.len(), TRIP_FEATURE_NAMES.len());
        // 100 ln(1.01) = 0.995: all in the middle segment.
        assert_eq!(f[0], 0.0);
        assert!((f[1] - 100.0 * 1.01f64.ln()).abs() < 1e-12);
        assert_eq!(f[2], 0.0);
        assert_eq!(f[9], 0.0);
        // No local route through the match (ratio 0) is the bottom of the scale; a ratio far
        // above saturates at 5.
        assert_eq!(ratio_segments(0.0), [-3.0, 0.0, 0.0]);
        assert_eq!(ratio_segments(0.5), [-3.0, 0.0, 0.0]);
        assert_eq!(ratio_segments(2.0), [0.0, 2.0, 3.0]);
        let unknown = FrameEvidence {
            step_spread: f64::NAN,
            prior: 0.0,
            dwell: 0,
            later: 0,
            since_jump: 1000,
            ..evidence(1.0)
        };
        let f = trip_features(&unknown, 2);
        assert_eq!(f[3], 0.0);
        assert_eq!(f[5], 1.0);
        assert_eq!(f[6], 1.0);
        assert_eq!(f[7], 2.0);
        // ln(0.05) = -3.0, clamped at -2.
        assert_eq!(f[8], -2.0);
        assert!((f[9] - 2f64.ln()).abs() < 1e-12);
        let p = PredictionEvidence {
            stretch_min: f64::NAN,
            step_spread: f64::NAN,
            rank: 1,
            contrast: f64::INFINITY,
            ..prediction(1.0)
        };
        let f = offline_features(&p, 1);
        assert_eq!(f.len(), OFFLINE_FEATURE_NAMES.len());
        assert_eq!(f[3], 1.0);
        assert_eq!(f[4], 10.0);
        assert_eq!(f[6], f[5]);
        assert_eq!(f[7], 2.0);
    }

    #[test]
    fn statuses_follow_the_threshold_the_evidence_and_the_reference() {
        let ev = evidence(1.02);
        let s = |r: Option<usize>, p: f64, ev: &FrameEvidence| frame_status(r, p, ev, 0.9, 10);
        assert_eq!(s(Some(40), 0.95, &ev), FrameStatus::Localized);
        assert_eq!(s(Some(40), 0.9, &ev), FrameStatus::Localized);
        assert_eq!(s(Some(40), 0.89, &ev), FrameStatus::Uncertain);
        assert_eq!(s(None, 0.0, &ev), FrameStatus::OffMap);
        // Not enough evidence yet, or relocalizing: lost, with or without a reference.
        let early = FrameEvidence { frame: 3, ..ev };
        let jumped = FrameEvidence {
            since_jump: 4,
            ..ev
        };
        for e in [&early, &jumped] {
            assert_eq!(s(Some(40), 0.5, e), FrameStatus::Lost);
            assert_eq!(s(None, 0.0, e), FrameStatus::Lost);
            // A reference the evidence already supports is localized all the same.
            assert_eq!(s(Some(40), 0.97, e), FrameStatus::Localized);
        }
        // Without a reference nothing is localized, whatever p.
        assert_eq!(s(None, 1.0, &ev), FrameStatus::OffMap);
        let names: Vec<&str> = [
            FrameStatus::Localized,
            FrameStatus::Uncertain,
            FrameStatus::OffMap,
            FrameStatus::Lost,
        ]
        .iter()
        .map(|s| s.as_str())
        .collect();
        assert_eq!(names, ["localized", "uncertain", "off_map", "lost"]);
    }
}
