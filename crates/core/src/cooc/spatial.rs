//! Spatial words: the quantised arrangement of a feature pair (Section II-A and III-B).
//!
//! The image is divided into a `cols x rows` grid of cells (the paper: 12 x 8 = 96). The offset
//! from feature `a` to feature `b` is measured in whole cells per axis (`|dx|`, `|dy|`), and the
//! relation says whether `b` lies left or right of `a`, and above or below it. A spatial word is
//! the triple (relation, |dx|, |dy|): `4 * cols * rows` words, 384 for the paper's grid.
//! Only relative positions matter, so a lateral shift of the camera keeps the words (the paper's
//! Figure 11 argument).
//!
//! Invariants: `word(a, b)` is always `< len()`; the signed offset of `word(a, b)` is the negated
//! signed offset of `word(b, a)`; positions are normalised to `[0, 1)`.

use crate::{Error, Result};

/// A spatial word id, `< SpatialGrid::len()`.
pub type SpatialWord = u16;

/// The spatial grid and its dictionary.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SpatialGrid {
    cols: u16,
    rows: u16,
}

impl SpatialGrid {
    /// A grid of `cols x rows` cells; both in `1..=64`.
    pub fn new(cols: u16, rows: u16) -> Result<Self> {
        for (name, v) in [("grid_cols", cols), ("grid_rows", rows)] {
            if !(1..=64).contains(&v) {
                return Err(Error::param(name, format!("must be in 1..=64, got {v}")));
            }
        }
        Ok(SpatialGrid { cols, rows })
    }

    /// Size of the spatial dictionary: `4 * cols * rows`.
    pub fn len(&self) -> usize {
        4 * self.cols as usize * self.rows as usize
    }

    /// Never true (a grid has at least one cell).
    pub fn is_empty(&self) -> bool {
        false
    }

    /// The spatial word of the pair `a -> b` (normalised positions `(x, y)`).
    #[inline]
    pub fn word(&self, a: (f32, f32), b: (f32, f32)) -> SpatialWord {
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let ax = ((dx.abs() * self.cols as f32) as u16).min(self.cols - 1);
        let ay = ((dy.abs() * self.rows as f32) as u16).min(self.rows - 1);
        let relation = u16::from(dx < 0.0) | (u16::from(dy < 0.0) << 1);
        (relation * self.rows + ay) * self.cols + ax
    }

    /// The signed cell offset `(dx, dy)` a word stands for (left/above = negative).
    #[inline]
    pub fn offset(&self, w: SpatialWord) -> (i16, i16) {
        let ax = (w % self.cols) as i16;
        let rest = w / self.cols;
        let ay = (rest % self.rows) as i16;
        let relation = rest / self.rows;
        let sx = if relation & 1 != 0 { -ax } else { ax };
        let sy = if relation & 2 != 0 { -ay } else { ay };
        (sx, sy)
    }

    /// Whether a stored word and an observed word agree within `tolerance` cells per axis.
    /// Tolerance 0 compares signed offsets exactly, so a sub-cell offset on either side of zero
    /// counts as the same arrangement.
    #[inline]
    pub fn consistent(&self, stored: SpatialWord, observed: (i16, i16), tolerance: u16) -> bool {
        let (sx, sy) = self.offset(stored);
        let t = tolerance as i16;
        (sx - observed.0).abs() <= t && (sy - observed.1).abs() <= t
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn paper_grid_has_384_words() {
        assert_eq!(SpatialGrid::new(12, 8).unwrap().len(), 384);
        assert!(SpatialGrid::new(0, 8).is_err());
    }

    #[test]
    fn relations_and_distances() {
        let g = SpatialGrid::new(12, 8).unwrap();
        // b is 3 cells right and 2 cells below a.
        let w = g.word((0.1, 0.1), (0.1 + 3.5 / 12.0, 0.1 + 2.5 / 8.0));
        assert_eq!(g.offset(w), (3, 2));
        // Left and above.
        let w = g.word((0.9, 0.9), (0.9 - 5.5 / 12.0, 0.9 - 1.5 / 8.0));
        assert_eq!(g.offset(w), (-5, -1));
        assert!(g.consistent(w, (-5, -1), 0));
        assert!(!g.consistent(w, (-4, -1), 0));
        assert!(g.consistent(w, (-4, -2), 1));
    }

    proptest! {
        #[test]
        fn words_are_in_range_and_antisymmetric(
            ax in 0.0f32..1.0, ay in 0.0f32..1.0, bx in 0.0f32..1.0, by in 0.0f32..1.0,
            cols in 1u16..20, rows in 1u16..20,
        ) {
            let g = SpatialGrid::new(cols, rows).unwrap();
            let ab = g.word((ax, ay), (bx, by));
            let ba = g.word((bx, by), (ax, ay));
            prop_assert!((ab as usize) < g.len());
            let (o1, o2) = (g.offset(ab), g.offset(ba));
            prop_assert_eq!((o1.0, o1.1), (-o2.0, -o2.1));
            // Translation invariance up to quantisation: shifting both keeps |offset| within 1.
            let t = 0.013f32;
            if ax + t < 1.0 && bx + t < 1.0 {
                let s = g.offset(g.word((ax + t, ay), (bx + t, by)));
                prop_assert!((s.0 - o1.0).abs() <= 1 && s.1 == o1.1);
            }
        }
    }
}
