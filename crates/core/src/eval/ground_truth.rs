//! Ground truth (which reference images show the place of each query) and query exclusions.
//!
//! [`GroundTruth`] is read from a CSV whose header has at least `query_index` and `ref_index`
//! (any order, other columns ignored, surrounding spaces trimmed). A query may have several rows
//! (several true references); a query with no row has no true match. It is stored sparsely
//! (query -> sorted, de-duplicated references), so huge indices cost nothing.
//!
//! [`Exclusions`] are query index ranges left out of scoring, written like `0-16,100-120,5`
//! (inclusive ranges and single indices), e.g. Nordland's filler frames 0-16.

use std::collections::BTreeMap;
use std::path::Path;

use crate::{Error, Result};

/// True reference indices per query.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct GroundTruth {
    matches: BTreeMap<usize, Vec<usize>>,
}

impl GroundTruth {
    /// The largest query index with a ground-truth row, if any.
    pub fn max_query_index(&self) -> Option<usize> {
        self.matches.keys().next_back().copied()
    }

    /// The largest reference index any ground-truth row names, if any.
    pub fn max_reference_index(&self) -> Option<usize> {
        self.matches
            .values()
            .filter_map(|refs| refs.last())
            .max()
            .copied()
    }

    /// Ground truth from `(query_index, ref_index)` pairs (several per query allowed).
    pub fn from_pairs(pairs: impl IntoIterator<Item = (usize, usize)>) -> Self {
        let mut matches: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
        for (q, r) in pairs {
            matches.entry(q).or_default().push(r);
        }
        for refs in matches.values_mut() {
            refs.sort_unstable();
            refs.dedup();
        }
        GroundTruth { matches }
    }

    /// Reads a ground-truth CSV. Errors ([`Error::Format`] naming the file and line) for an
    /// empty file, a header without `query_index` or `ref_index`, a value that is not a
    /// non-negative integer, a row missing the column, or a file without data rows.
    pub fn from_csv(path: &Path) -> Result<Self> {
        let format = |reason: String| Error::Format {
            path: path.to_path_buf(),
            reason,
        };
        let file = std::fs::File::open(path).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let mut reader = csv::ReaderBuilder::new()
            .has_headers(true)
            .trim(csv::Trim::All)
            .flexible(true)
            .from_reader(std::io::BufReader::new(file));
        let headers = reader
            .headers()
            .map_err(|e| format(format!("line 1: cannot read the header: {e}")))?
            .clone();
        if headers.is_empty() || headers.iter().all(str::is_empty) {
            return Err(format(
                "file is empty (expected a header with query_index,ref_index)".into(),
            ));
        }
        let column = |name: &str| {
            headers.iter().position(|h| h == name).ok_or_else(|| {
                format(format!(
                    "line 1: header has no `{name}` column (found: {})",
                    headers.iter().collect::<Vec<_>>().join(",")
                ))
            })
        };
        let (qcol, rcol) = (column("query_index")?, column("ref_index")?);
        let mut pairs = Vec::new();
        for record in reader.records() {
            let record = record.map_err(|e| {
                let line = e.position().map_or(0, |p| p.line());
                format(format!("line {line}: {e}"))
            })?;
            let line = record.position().map_or(0, |p| p.line());
            if record.iter().all(str::is_empty) {
                continue;
            }
            let field = |col: usize, name: &str| -> Result<usize> {
                let raw = record
                    .get(col)
                    .ok_or_else(|| format(format!("line {line}: no `{name}` value")))?;
                raw.parse::<usize>().map_err(|_| {
                    format(format!(
                        "line {line}: `{name}` is `{raw}`, not a non-negative integer"
                    ))
                })
            };
            pairs.push((field(qcol, "query_index")?, field(rcol, "ref_index")?));
        }
        if pairs.is_empty() {
            return Err(format("no ground-truth rows after the header".into()));
        }
        Ok(GroundTruth::from_pairs(pairs))
    }

    /// The true references of `query` (sorted; empty when it has no true match).
    pub fn references(&self, query: usize) -> &[usize] {
        self.matches.get(&query).map_or(&[], Vec::as_slice)
    }

    /// Whether `query` has at least one true reference.
    pub fn has_match(&self, query: usize) -> bool {
        self.matches.contains_key(&query)
    }

    /// Whether predicting `reference` for `query` is correct: `|reference - g| <= tolerance`
    /// for some true reference `g`.
    pub fn is_correct(&self, query: usize, reference: usize, tolerance: usize) -> bool {
        let refs = self.references(query);
        // Sorted: the nearest true reference is next to the insertion point.
        let k = refs.partition_point(|&g| g < reference);
        [k.checked_sub(1), Some(k)]
            .into_iter()
            .flatten()
            .filter_map(|idx| refs.get(idx))
            .any(|&g| g.abs_diff(reference) <= tolerance)
    }

    /// Number of queries with at least one true reference.
    pub fn len(&self) -> usize {
        self.matches.len()
    }

    /// Whether no query has a true reference.
    pub fn is_empty(&self) -> bool {
        self.matches.is_empty()
    }
}

/// Query indices excluded from scoring: a union of inclusive ranges.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Exclusions {
    /// Sorted, merged, inclusive `(start, end)` ranges.
    ranges: Vec<(usize, usize)>,
}

impl Exclusions {
    /// No exclusions.
    pub fn none() -> Self {
        Exclusions::default()
    }

    /// Parses `A-B` inclusive ranges and single indices separated by commas, e.g.
    /// `0-16,100-120,5`. An empty (or all-blank) string means no exclusions. Errors
    /// ([`Error::InvalidParameter`] `exclude`) for `A > B`, non-numbers and empty pieces.
    pub fn parse(spec: &str) -> Result<Self> {
        if spec.trim().is_empty() {
            return Ok(Exclusions::none());
        }
        let number = |s: &str, piece: &str| {
            s.trim().parse::<usize>().map_err(|_| {
                Error::param(
                    "exclude",
                    format!("`{}` in `{piece}` is not a non-negative integer", s.trim()),
                )
            })
        };
        let mut ranges = Vec::new();
        for piece in spec.split(',') {
            let piece = piece.trim();
            if piece.is_empty() {
                return Err(Error::param(
                    "exclude",
                    format!("empty piece in `{spec}` (expected A-B or A, separated by commas)"),
                ));
            }
            let (a, b) = match piece.split_once('-') {
                Some((a, b)) => (number(a, piece)?, number(b, piece)?),
                None => {
                    let a = number(piece, piece)?;
                    (a, a)
                }
            };
            if a > b {
                return Err(Error::param(
                    "exclude",
                    format!("range `{piece}` starts after it ends"),
                ));
            }
            ranges.push((a, b));
        }
        Ok(Exclusions::from_ranges(ranges))
    }

    /// Exclusions from inclusive `(start, end)` ranges; ranges with `start > end` are empty and
    /// dropped, overlapping or adjacent ranges are merged.
    pub fn from_ranges(ranges: impl IntoIterator<Item = (usize, usize)>) -> Self {
        let mut r: Vec<(usize, usize)> = ranges.into_iter().filter(|(a, b)| a <= b).collect();
        r.sort_unstable();
        let mut merged: Vec<(usize, usize)> = Vec::with_capacity(r.len());
        for (a, b) in r {
            match merged.last_mut() {
                Some(last) if a <= last.1.saturating_add(1) => last.1 = last.1.max(b),
                _ => merged.push((a, b)),
            }
        }
        Exclusions { ranges: merged }
    }

    /// Whether `query` is excluded.
    pub fn contains(&self, query: usize) -> bool {
        let k = self.ranges.partition_point(|&(_, b)| b < query);
        self.ranges.get(k).is_some_and(|&(a, _)| a <= query)
    }

    /// The merged inclusive ranges, sorted.
    pub fn ranges(&self) -> &[(usize, usize)] {
        &self.ranges
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn csv_file(text: &str) -> (tempfile::TempDir, std::path::PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("gt.csv");
        std::fs::File::create(&path)
            .unwrap()
            .write_all(text.as_bytes())
            .unwrap();
        (dir, path)
    }

    fn format_reason(text: &str) -> String {
        let (_dir, path) = csv_file(text);
        match GroundTruth::from_csv(&path) {
            Err(Error::Format { path: p, reason }) => {
                assert_eq!(p, path);
                reason
            }
            other => panic!("expected a format error, got {other:?}"),
        }
    }

    #[test]
    fn reads_columns_in_any_order_and_several_rows_per_query() {
        let (_dir, path) = csv_file(
            "ref_file,ref_index,query_index,query_file\n\
             a.png,10,0,x.png\n\
             b.png, 12 ,0,y.png\n\
             c.png,3,5,z.png\n",
        );
        let gt = GroundTruth::from_csv(&path).unwrap();
        assert_eq!(gt.references(0), &[10, 12]);
        assert_eq!(gt.references(5), &[3]);
        assert!(!gt.has_match(1));
        assert_eq!(gt.len(), 2);
        assert!(gt.is_correct(0, 11, 1) && gt.is_correct(0, 13, 1) && !gt.is_correct(0, 14, 1));
        assert!(gt.is_correct(5, 3, 0) && !gt.is_correct(5, 4, 0));
        assert!(!gt.is_correct(1, 0, 100));
    }

    #[test]
    fn csv_errors_name_the_line() {
        assert!(format_reason("").contains("empty"));
        let r = format_reason("query_index,ref\n0,1\n");
        assert!(r.contains("line 1") && r.contains("`ref_index`"), "{r}");
        let r = format_reason("query_index,ref_index\n0,1\n1,x\n");
        assert!(r.contains("line 3") && r.contains("`x`"), "{r}");
        let r = format_reason("query_index,ref_index\n0,-1\n");
        assert!(r.contains("line 2") && r.contains("ref_index"), "{r}");
        let r = format_reason("query_index,ref_index\n0\n");
        assert!(r.contains("line 2") && r.contains("no `ref_index`"), "{r}");
        assert!(format_reason("query_index,ref_index\n").contains("no ground-truth rows"));
    }

    #[test]
    fn missing_file_is_an_io_error_naming_it() {
        let err = GroundTruth::from_csv(Path::new("/nonexistent/gt.csv")).unwrap_err();
        assert!(matches!(err, Error::Io { .. }));
        assert!(err.to_string().contains("/nonexistent/gt.csv"));
    }

    #[test]
    fn parses_ranges_and_single_indices() {
        let e = Exclusions::parse(" 0-16, 100-120,5,17 ").unwrap();
        assert_eq!(e.ranges(), &[(0, 17), (100, 120)]);
        assert!(e.contains(0) && e.contains(16) && e.contains(17) && e.contains(110));
        assert!(!e.contains(18) && !e.contains(99) && !e.contains(121));
        assert_eq!(Exclusions::parse("").unwrap(), Exclusions::none());
        assert_eq!(Exclusions::parse("3-3").unwrap().ranges(), &[(3, 3)]);
    }

    #[test]
    fn exclusion_errors() {
        for (spec, needle) in [
            ("5-2", "starts after it ends"),
            ("a-3", "`a`"),
            ("1,,2", "empty piece"),
            ("1-", "``"),
            ("-4", "``"),
            ("1.5", "`1.5`"),
        ] {
            match Exclusions::parse(spec) {
                Err(Error::InvalidParameter { name, reason }) => {
                    assert_eq!(name, "exclude");
                    assert!(reason.contains(needle), "{spec}: {reason}");
                }
                other => panic!("{spec}: expected an exclude error, got {other:?}"),
            }
        }
    }
}
