//! Writing a method's predictions as CSV (`--predictions`): header
//! `query_index,ref_index,confidence,p_correct`, one row per predicted query, sorted by query;
//! `p_correct` is empty for a method without a calibration.
//!
//! Confidences are written with Rust's shortest round-trip formatting, so reading the file back
//! gives the same `f64` values (and the same metrics).

use std::io::Write;
use std::path::Path;

use super::Prediction;
use crate::{Error, Result};

/// Writes `predictions` to `path` (created or truncated), sorted by query index.
pub fn write_predictions_csv(path: &Path, predictions: &[Prediction]) -> Result<()> {
    let io_err = |source| Error::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut sorted = predictions.to_vec();
    sorted.sort_by_key(|p| (p.query, p.reference));
    let file = std::fs::File::create(path).map_err(io_err)?;
    let mut w = std::io::BufWriter::new(file);
    writeln!(w, "query_index,ref_index,confidence,p_correct").map_err(io_err)?;
    for p in &sorted {
        let p_correct = p.p_correct.map(|v| v.to_string()).unwrap_or_default();
        writeln!(
            w,
            "{},{},{},{p_correct}",
            p.query, p.reference, p.confidence
        )
        .map_err(io_err)?;
    }
    w.flush().map_err(io_err)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_header_and_rows_sorted_by_query() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("pred.csv");
        let p = [
            Prediction {
                query: 7,
                reference: 3,
                confidence: 0.25,
                p_correct: None,
            },
            Prediction {
                query: 2,
                reference: 9,
                confidence: 1.0 / 3.0,
                p_correct: Some(0.875),
            },
        ];
        write_predictions_csv(&path, &p).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "query_index,ref_index,confidence,p_correct");
        assert_eq!(lines[2], "7,3,0.25,");
        assert!(lines[1].ends_with(",0.875"), "{}", lines[1]);
        assert!(lines[1].starts_with("2,9,0.333"));
        let back: f64 = lines[1].split(',').nth(2).unwrap().parse().unwrap();
        assert_eq!(back, 1.0 / 3.0);
        assert_eq!(lines.len(), 3);
    }

    #[test]
    fn unwritable_path_names_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("missing-dir").join("pred.csv");
        let err = write_predictions_csv(&path, &[]).unwrap_err();
        assert!(matches!(err, Error::Io { .. }));
        assert!(err.to_string().contains("missing-dir"), "{err}");
    }
}
