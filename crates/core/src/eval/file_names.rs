//! Whether a ground truth describes the folders it is scored against: the optional
//! `query_file` and `ref_file` columns of a ground-truth CSV (e.g. Nordland's
//! `winter/images-00010.png`) are compared with the file at that index of the query and
//! reference folders (by file name; the folder part may differ, folders get renamed).
//!
//! Why: indices alone always "fit" — a ground truth of another dataset (its `query_file` names
//! `night_right/Image000.jpg` while the queries are Nordland PNGs) was scored to AP 0.0 without
//! a word. The check reports how many rows name other files and the first of them; the command
//! warns, and refuses with `--strict`.

use std::path::{Path, PathBuf};

use crate::{Error, Result};

/// One ground-truth row's file columns (absent columns are `None`).
#[derive(Clone, Debug, PartialEq, Eq)]
struct NamedRow {
    line: u64,
    query: usize,
    query_file: Option<String>,
    reference: usize,
    ref_file: Option<String>,
}

/// The file columns of a ground-truth CSV.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct GroundTruthFiles {
    rows: Vec<NamedRow>,
}

/// What [`GroundTruthFiles::check`] found.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FileNameCheck {
    /// Rows whose file columns were compared.
    pub checked: usize,
    /// Of those, rows naming a file other than the folder's file at that index.
    pub mismatched: usize,
    /// The first mismatch, said for a person (line, column, named file, folder's file).
    pub first: Option<String>,
}

impl FileNameCheck {
    /// Whether every compared row names the folders' files (true when nothing was compared).
    pub fn holds(&self) -> bool {
        self.mismatched == 0
    }
}

impl GroundTruthFiles {
    /// Reads the `query_index`, `query_file`, `ref_index` and `ref_file` columns of a
    /// ground-truth CSV; a file without either file column gives no rows (nothing to check).
    /// Rows the ground truth itself refuses are left to [`crate::eval::GroundTruth::from_csv`].
    pub fn from_csv(path: &Path) -> Result<Self> {
        let file = std::fs::File::open(path).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let mut reader = csv::ReaderBuilder::new()
            .has_headers(true)
            .trim(csv::Trim::All)
            .flexible(true)
            .from_reader(std::io::BufReader::new(file));
        let Ok(headers) = reader.headers().cloned() else {
            return Ok(GroundTruthFiles::default());
        };
        let col = |name: &str| headers.iter().position(|h| h == name);
        let (Some(qi), Some(ri)) = (col("query_index"), col("ref_index")) else {
            return Ok(GroundTruthFiles::default());
        };
        let (qf, rf) = (col("query_file"), col("ref_file"));
        if qf.is_none() && rf.is_none() {
            return Ok(GroundTruthFiles::default());
        }
        let mut rows = Vec::new();
        for record in reader.records().flatten() {
            let index = |c: usize| record.get(c).and_then(|v| v.parse::<usize>().ok());
            let name = |c: Option<usize>| {
                c.and_then(|c| record.get(c))
                    .filter(|v| !v.is_empty())
                    .map(str::to_owned)
            };
            if let (Some(query), Some(reference)) = (index(qi), index(ri)) {
                rows.push(NamedRow {
                    line: record.position().map_or(0, |p| p.line()),
                    query,
                    query_file: name(qf),
                    reference,
                    ref_file: name(rf),
                });
            }
        }
        Ok(GroundTruthFiles { rows })
    }

    /// Compares each row's file columns with `queries[query_index]` and
    /// `references[ref_index]` (file names only). Indices past a folder's end are not counted
    /// here: the caller refuses them already.
    pub fn check(&self, queries: &[PathBuf], references: &[PathBuf]) -> FileNameCheck {
        let mut out = FileNameCheck {
            checked: 0,
            mismatched: 0,
            first: None,
        };
        for row in &self.rows {
            let sides = [
                (
                    "query_file",
                    &row.query_file,
                    queries.get(row.query),
                    row.query,
                ),
                (
                    "ref_file",
                    &row.ref_file,
                    references.get(row.reference),
                    row.reference,
                ),
            ];
            let mut compared = false;
            let mut wrong = None;
            for (column, named, actual, index) in sides {
                let (Some(named), Some(actual)) = (named, actual) else {
                    continue;
                };
                compared = true;
                let named_name = Path::new(named).file_name();
                if named_name != actual.file_name() && wrong.is_none() {
                    wrong = Some(format!(
                        "line {}: {column} is `{named}`, but image {index} of {} is `{}`",
                        row.line,
                        actual.parent().map_or(Path::new("."), |p| p).display(),
                        actual
                            .file_name()
                            .map_or_else(String::new, |n| n.to_string_lossy().into_owned())
                    ));
                }
            }
            if compared {
                out.checked += 1;
            }
            if let Some(w) = wrong {
                out.mismatched += 1;
                out.first.get_or_insert(w);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn files(dir: &str, names: &[&str]) -> Vec<PathBuf> {
        names.iter().map(|n| Path::new(dir).join(n)).collect()
    }

    fn write(text: &str) -> (tempfile::TempDir, PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("gt.csv");
        std::fs::write(&path, text).unwrap();
        (dir, path)
    }

    #[test]
    fn rows_naming_the_folders_files_hold_and_foreign_ones_are_counted() {
        let queries = files("/d/winter", &["images-00010.png", "images-00020.png"]);
        let refs = files("/d/summer", &["images-00010.png", "images-00020.png"]);
        let (_d, own) = write(
            "query_index,query_file,ref_index,ref_file\n\
             0,winter/images-00010.png,0,summer/images-00010.png\n\
             1,renamed/images-00020.png,1,summer/images-00020.png\n",
        );
        let c = GroundTruthFiles::from_csv(&own)
            .unwrap()
            .check(&queries, &refs);
        assert_eq!((c.checked, c.mismatched, c.holds()), (2, 0, true));

        let (_d, foreign) = write(
            "query_index,query_file,ref_index,ref_file\n\
             0,night_right/Image000.jpg,0,day_right/Image000.jpg\n\
             1,night_right/Image001.jpg,1,summer/images-00020.png\n",
        );
        let c = GroundTruthFiles::from_csv(&foreign)
            .unwrap()
            .check(&queries, &refs);
        assert_eq!((c.checked, c.mismatched, c.holds()), (2, 2, false));
        let first = c.first.unwrap();
        assert!(
            first.contains("line 2") && first.contains("night_right/Image000.jpg"),
            "{first}"
        );
        assert!(first.contains("images-00010.png"), "{first}");
    }

    #[test]
    fn a_ground_truth_without_file_columns_has_nothing_to_check() {
        let (_d, plain) = write("query_index,ref_index\n0,0\n1,1\n");
        let c = GroundTruthFiles::from_csv(&plain).unwrap().check(
            &files("/q", &["a.png", "b.png"]),
            &files("/r", &["a.png", "b.png"]),
        );
        assert_eq!((c.checked, c.mismatched, c.holds()), (0, 0, true));
    }
}
