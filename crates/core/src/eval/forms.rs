//! The field's ground-truth forms, beside seasonloc's CSV ([`GroundTruth::from_csv`]): each is
//! turned into the one [`GroundTruth`], so every form gives the same scores as the equivalent
//! CSV. Reading the files (NumPy `.npy` / `.npz`, pickled object arrays) is the callers' (the
//! CLI's `npy` module, the Python package); the forms' meaning lives here, once.
//!
//! * VPR-Bench's `ground_truth_new.npy`: one row per query, `[query index, [true reference
//!   indices]]` ([`GroundTruth::from_query_lists`]).
//! * VPR_Tutorial's `GThard` / `GTsoft`: a boolean references x queries matrix, `true` where
//!   the reference shows the query's place ([`GroundTruth::from_match_matrix`]).
//! * VPR-methods-evaluation's folder layout: `database/` and `queries/` images whose file names
//!   carry UTM coordinates (`@east@north@...`); a reference is a true match within a distance
//!   in metres, 25 m by default there ([`utm_of_file_name`], [`GroundTruth::within_distance`]).

use std::path::Path;

use super::GroundTruth;
use crate::{Error, Result};

/// VPR-methods-evaluation's default `positive_dist_threshold`, in metres.
pub const DEFAULT_POSITIVE_DISTANCE_M: f64 = 25.0;

impl GroundTruth {
    /// VPR-Bench's form: `(query, true references)` per row; a row with no reference gives the
    /// query no true match. Errors ([`Error::Empty`]) when no row names a reference.
    pub fn from_query_lists(rows: &[(usize, Vec<usize>)]) -> Result<Self> {
        let gt = GroundTruth::from_pairs(
            rows.iter()
                .flat_map(|(q, refs)| refs.iter().map(move |&r| (*q, r))),
        );
        if gt.is_empty() {
            return Err(Error::Empty(
                "the ground truth's rows name no true reference".into(),
            ));
        }
        Ok(gt)
    }

    /// VPR_Tutorial's form: `matches` is a `references x queries` boolean matrix in row-major
    /// order (`matches[r * queries + q]`: reference `r` shows the place of query `q`). Errors:
    /// a length other than `references * queries` ([`Error::Shape`]), no true entry
    /// ([`Error::Empty`]).
    pub fn from_match_matrix(references: usize, queries: usize, matches: &[bool]) -> Result<Self> {
        if references.checked_mul(queries) != Some(matches.len()) {
            return Err(Error::Shape(format!(
                "a {references} x {queries} ground-truth matrix needs {} values, got {}",
                references.saturating_mul(queries),
                matches.len()
            )));
        }
        let pairs = matches
            .iter()
            .enumerate()
            .filter(|&(_, &m)| m)
            .map(|(k, _)| (k % queries.max(1), k / queries.max(1)));
        let gt = GroundTruth::from_pairs(pairs);
        if gt.is_empty() {
            return Err(Error::Empty(
                "the ground-truth matrix (references x queries) has no true entry".into(),
            ));
        }
        Ok(gt)
    }

    /// VPR-methods-evaluation's rule: reference `r` is a true match of query `q` when their
    /// positions (UTM east, north, in metres) are at most `metres` apart. Errors: a distance
    /// that is not finite and >= 0 ([`Error::InvalidParameter`] `distance`), a non-finite
    /// position ([`Error::NonFinite`]), no query with a reference that close ([`Error::Empty`]).
    pub fn within_distance(
        references: &[(f64, f64)],
        queries: &[(f64, f64)],
        metres: f64,
    ) -> Result<Self> {
        if !(metres.is_finite() && metres >= 0.0) {
            return Err(Error::param(
                "distance",
                format!("must be a finite number of metres >= 0, got {metres}"),
            ));
        }
        for (what, points) in [
            ("reference position", references),
            ("query position", queries),
        ] {
            if let Some((i, &(e, n))) = points
                .iter()
                .enumerate()
                .find(|(_, (e, n))| !(e.is_finite() && n.is_finite()))
            {
                let (col, value) = if e.is_finite() { (1, n) } else { (0, e) };
                return Err(Error::NonFinite {
                    what,
                    row: i,
                    col,
                    value,
                });
            }
        }
        let limit = metres * metres;
        let pairs = queries.iter().enumerate().flat_map(|(q, &(qe, qn))| {
            references
                .iter()
                .enumerate()
                .filter(move |&(_, &(re, rn))| (re - qe).powi(2) + (rn - qn).powi(2) <= limit)
                .map(move |(r, _)| (q, r))
        });
        let gt = GroundTruth::from_pairs(pairs);
        if gt.is_empty() {
            return Err(Error::Empty(format!(
                "no query has a reference within {metres} m"
            )));
        }
        Ok(gt)
    }
}

/// The UTM position (east, north, metres) in a VPR-methods-evaluation file name,
/// `@east@north@zone@letter@lat@lon@...`: the first two `@`-separated fields after the
/// leading one. `None` when the name does not have that form.
pub fn utm_of_file_name(name: &str) -> Option<(f64, f64)> {
    let mut fields = name.split('@').skip(1);
    let east = fields.next()?.parse::<f64>().ok()?;
    let north = fields.next()?.parse::<f64>().ok()?;
    (east.is_finite() && north.is_finite()).then_some((east, north))
}

/// [`utm_of_file_name`] of every path's file name; errors ([`Error::Format`] naming the file)
/// at the first name without UTM coordinates.
pub fn utm_of_files(paths: &[impl AsRef<Path>]) -> Result<Vec<(f64, f64)>> {
    paths
        .iter()
        .map(|p| {
            let p = p.as_ref();
            p.file_name()
                .and_then(|n| n.to_str())
                .and_then(utm_of_file_name)
                .ok_or_else(|| Error::Format {
                    path: p.to_path_buf(),
                    reason: "the file name has no UTM coordinates (VPR-methods-evaluation's \
                             `@east@north@...` form)"
                        .into(),
                })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_form_gives_the_csv_ground_truth() {
        let csv_like = GroundTruth::from_pairs([(0, 0), (0, 2), (1, 1), (3, 2)]);
        let lists = GroundTruth::from_query_lists(&[
            (0, vec![2, 0]),
            (1, vec![1]),
            (2, vec![]),
            (3, vec![2]),
        ])
        .unwrap();
        assert_eq!(lists, csv_like);
        // 3 references x 4 queries.
        #[rustfmt::skip]
        let m = [
            true,  false, false, false,
            false, true,  false, false,
            true,  false, false, true,
        ];
        assert_eq!(GroundTruth::from_match_matrix(3, 4, &m).unwrap(), csv_like);
        assert!(matches!(
            GroundTruth::from_match_matrix(3, 3, &m),
            Err(Error::Shape(_))
        ));
        assert!(GroundTruth::from_match_matrix(2, 2, &[false; 4]).is_err());
        assert!(GroundTruth::from_query_lists(&[(0, vec![])]).is_err());
    }

    #[test]
    fn utm_names_and_distances() {
        let name = "@0543256.19@4178781.24@10@S@37.75@-122.51@pano@@@@@@@.jpg";
        assert_eq!(utm_of_file_name(name), Some((543256.19, 4178781.24)));
        assert_eq!(utm_of_file_name("images-00010.png"), None);
        let refs = [(0.0, 0.0), (20.0, 0.0), (100.0, 0.0)];
        let queries = [(0.0, 15.0), (60.0, 0.0), (100.0, 25.0)];
        let gt = GroundTruth::within_distance(&refs, &queries, 25.0).unwrap();
        // q0: 15 m from r0, 25 m from r1 (inclusive); q1: none; q2: exactly 25 m from r2.
        assert_eq!(gt, GroundTruth::from_pairs([(0, 0), (0, 1), (2, 2)]));
        assert!(GroundTruth::within_distance(&refs, &queries, f64::NAN).is_err());
        assert!(GroundTruth::within_distance(&refs, &[(500.0, 0.0)], 25.0).is_err());
        let err = utm_of_files(&["db/@1@2@.jpg", "db/x.jpg"]).unwrap_err();
        assert!(err.to_string().contains("db/x.jpg"), "{err}");
    }
}
