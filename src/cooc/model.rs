//! Location models (Section II-B) and the map of all locations with its inverted index.
//!
//! A location's word-co-occurrence matrix `M_i` has one row per visual word seen there (a lookup
//! table maps rows to words) and, for each word pair, the *set* of spatial words in which the
//! pair was observed. It is stored sparsely: `words` (sorted, row `r` is `words[r]`) and `pairs`,
//! a sorted list of packed `(row_a, row_b, spatial word)` entries with `row_a <= row_b` and the
//! spatial word oriented from `a` to `b` (for `row_a == row_b` both orientations are stored), so
//! a lookup is one binary search and the matrix takes 8 bytes per distinct entry.
//!
//! [`LocationMap`] keeps, per mapping drive, the quantised features it saw at each location, and
//! derives the models from them: every image's own pairs, plus — with merging on — the pairs of
//! the union of the images of two drives adjacent in time at that location (Section II-E), which
//! adds the cross-drive co-occurrences that an intermediate time of day would show.
//!
//! Invariants: `models.len() == locations()`; the inverted index lists `(location, row)` for
//! exactly the words in each model; drives are kept in time order (stable for equal times).

use super::spatial::SpatialGrid;
use crate::{Error, Result};

/// A quantised feature: its visual word and its position (normalised, 16-bit fixed point).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Word {
    /// Visual word id.
    pub word: u32,
    /// Horizontal position in units of 1/65536 of the image width.
    pub x: u16,
    /// Vertical position in units of 1/65536 of the image height.
    pub y: u16,
}

impl Word {
    /// A feature at normalised position `(x, y)` (clamped to `[0, 1)`).
    pub fn new(word: u32, x: f32, y: f32) -> Self {
        let q = |v: f32| (v.clamp(0.0, 1.0) * 65536.0).min(65535.0) as u16;
        Word {
            word,
            x: q(x),
            y: q(y),
        }
    }

    /// Normalised position `(x, y)`.
    #[inline]
    pub fn pos(&self) -> (f32, f32) {
        (self.x as f32 / 65536.0, self.y as f32 / 65536.0)
    }
}

/// Largest number of locations a map may have (4M images: weeks of driving at 1 fps); bounds
/// the memory a corrupt or hostile location index can claim.
pub const MAX_LOCATIONS: usize = 1 << 22;

const ROW_BITS: u32 = 24;
const MAX_ROWS: usize = 1 << ROW_BITS;

#[inline]
fn pack(a: u32, b: u32, s: u16) -> u64 {
    (u64::from(a) << 40) | (u64::from(b) << 16) | u64::from(s)
}

/// The word-co-occurrence matrix `M_i` of one location.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LocationModel {
    words: Vec<u32>,
    pairs: Vec<u64>,
}

impl LocationModel {
    /// Builds `M_i` from "images" (feature sets): every pair within one set is recorded.
    pub fn build(sets: &[Vec<Word>], grid: &SpatialGrid) -> Result<Self> {
        let mut words: Vec<u32> = sets.iter().flatten().map(|f| f.word).collect();
        words.sort_unstable();
        words.dedup();
        if words.len() > MAX_ROWS {
            return Err(Error::Shape(format!(
                "a location has {} distinct words, more than {MAX_ROWS}",
                words.len()
            )));
        }
        let row = |w: u32| words.binary_search(&w).expect("word collected above") as u32;
        let mut pairs = Vec::new();
        for set in sets {
            let rows: Vec<u32> = set.iter().map(|f| row(f.word)).collect();
            for i in 0..set.len() {
                for j in i + 1..set.len() {
                    let (pi, pj) = (set[i].pos(), set[j].pos());
                    let (ri, rj) = (rows[i], rows[j]);
                    if ri < rj {
                        pairs.push(pack(ri, rj, grid.word(pi, pj)));
                    } else if rj < ri {
                        pairs.push(pack(rj, ri, grid.word(pj, pi)));
                    } else {
                        pairs.push(pack(ri, rj, grid.word(pi, pj)));
                        pairs.push(pack(ri, rj, grid.word(pj, pi)));
                    }
                }
            }
        }
        pairs.sort_unstable();
        pairs.dedup();
        Ok(LocationModel { words, pairs })
    }

    /// The visual words with a row in `M_i`, sorted (row `r` is `words()[r]`).
    pub fn words(&self) -> &[u32] {
        &self.words
    }

    /// Number of distinct `(word pair, spatial word)` entries.
    pub fn entries(&self) -> usize {
        self.pairs.len()
    }

    /// The row of visual word `w`, if it was seen here.
    pub fn row(&self, w: u32) -> Option<u32> {
        self.words.binary_search(&w).ok().map(|r| r as u32)
    }

    /// Whether rows `a` and `b` co-occurred with a spatial word matching `observed` (the signed
    /// cell offset from `a`'s feature to `b`'s in the query) within `tolerance`.
    #[inline]
    pub fn consistent(
        &self,
        a: u32,
        b: u32,
        observed: (i16, i16),
        grid: &SpatialGrid,
        tolerance: u16,
    ) -> bool {
        let (lo, hi, obs) = if a <= b {
            (a, b, observed)
        } else {
            (b, a, (-observed.0, -observed.1))
        };
        let start = pack(lo, hi, 0);
        let first = self.pairs.partition_point(|&p| p < start);
        self.pairs[first..]
            .iter()
            .take_while(|&&p| p >> 16 == start >> 16)
            .any(|&p| grid.consistent((p & 0xffff) as u16, obs, tolerance))
    }
}

/// What one mapping drive saw: its time and, per location, its images' quantised features.
#[derive(Clone, Debug, PartialEq)]
pub struct DriveRecord {
    /// Time key of the drive (e.g. hours since midnight or a timestamp); only the order matters.
    pub time: f64,
    /// `(location, features)` per image, in the order given.
    pub images: Vec<(u32, Vec<Word>)>,
}

/// All location models of a route, the drives they were built from, and the inverted index.
#[derive(Clone, Debug, PartialEq)]
pub struct LocationMap {
    grid: SpatialGrid,
    tolerance: u16,
    merge_adjacent: bool,
    drives: Vec<DriveRecord>,
    models: Vec<LocationModel>,
    /// `index[w]` = `(location, row)` of every model that has word `w`, by location.
    index: Vec<Vec<(u32, u32)>>,
}

impl LocationMap {
    /// An empty map.
    pub fn new(grid: SpatialGrid, tolerance: u16, merge_adjacent: bool) -> Self {
        LocationMap {
            grid,
            tolerance,
            merge_adjacent,
            drives: Vec::new(),
            models: Vec::new(),
            index: Vec::new(),
        }
    }

    /// Adds one drive; locations beyond the current end extend the route. The models of the
    /// locations it observed are rebuilt (with its neighbours in time), then the index.
    pub fn add_drive(&mut self, drive: DriveRecord) -> Result<()> {
        if !drive.time.is_finite() {
            return Err(Error::param(
                "time",
                format!("a drive's time must be finite, got {}", drive.time),
            ));
        }
        if let Some((l, _)) = drive
            .images
            .iter()
            .find(|(l, _)| *l as usize >= MAX_LOCATIONS)
        {
            return Err(Error::param(
                "locations",
                format!("location {l} is beyond the limit of {MAX_LOCATIONS} locations"),
            ));
        }
        let mut touched: Vec<u32> = drive.images.iter().map(|(l, _)| *l).collect();
        touched.sort_unstable();
        touched.dedup();
        let pos = self.drives.partition_point(|d| d.time <= drive.time);
        self.drives.insert(pos, drive);
        let needed = touched.last().map_or(0, |&l| l as usize + 1);
        if needed > self.models.len() {
            self.models.resize(needed, LocationModel::default());
        }
        for &loc in &touched {
            self.models[loc as usize] = self.build_model(loc)?;
        }
        self.rebuild_index();
        Ok(())
    }

    /// The feature sets ("virtual images") of one location, per Section II-E.
    fn virtual_images(&self, loc: u32) -> Vec<Vec<Word>> {
        let per_drive: Vec<Vec<&Vec<Word>>> = self
            .drives
            .iter()
            .map(|d| {
                d.images
                    .iter()
                    .filter(|(l, _)| *l == loc)
                    .map(|(_, f)| f)
                    .collect::<Vec<_>>()
            })
            .filter(|v: &Vec<&Vec<Word>>| !v.is_empty())
            .collect();
        let mut sets: Vec<Vec<Word>> = per_drive.iter().flatten().map(|f| (*f).clone()).collect();
        if self.merge_adjacent {
            for pair in per_drive.windows(2) {
                for a in &pair[0] {
                    for b in &pair[1] {
                        sets.push(a.iter().chain(b.iter()).copied().collect());
                    }
                }
            }
        }
        sets
    }

    fn build_model(&self, loc: u32) -> Result<LocationModel> {
        LocationModel::build(&self.virtual_images(loc), &self.grid)
    }

    fn rebuild_index(&mut self) {
        let top = self
            .models
            .iter()
            .filter_map(|m| m.words.last())
            .max()
            .map_or(0, |&w| w as usize + 1);
        let mut index: Vec<Vec<(u32, u32)>> = vec![Vec::new(); top];
        for (loc, m) in self.models.iter().enumerate() {
            for (row, &w) in m.words.iter().enumerate() {
                index[w as usize].push((loc as u32, row as u32));
            }
        }
        self.index = index;
    }

    /// Number of locations.
    pub fn locations(&self) -> usize {
        self.models.len()
    }

    /// The model of location `loc`.
    pub fn model(&self, loc: usize) -> &LocationModel {
        &self.models[loc]
    }

    /// The drives, in time order.
    pub fn drives(&self) -> &[DriveRecord] {
        &self.drives
    }

    /// The spatial grid.
    pub fn grid(&self) -> &SpatialGrid {
        &self.grid
    }

    /// Spatial tolerance in cells.
    pub fn tolerance(&self) -> u16 {
        self.tolerance
    }

    /// Whether adjacent drives are merged.
    pub fn merges_adjacent(&self) -> bool {
        self.merge_adjacent
    }

    /// Postings of visual word `w`: `(location, row)`, by location.
    pub fn postings(&self, w: u32) -> &[(u32, u32)] {
        self.index.get(w as usize).map_or(&[], |v| v.as_slice())
    }

    /// Total `(word pair, spatial word)` entries over all models.
    pub fn entries(&self) -> usize {
        self.models.iter().map(|m| m.entries()).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> SpatialGrid {
        SpatialGrid::new(12, 8).unwrap()
    }

    #[test]
    fn paper_figure_4_pairs_are_recorded_both_ways() {
        // A left of B in one image, A bottom-right of B in another (Figure 4's example).
        let img1 = vec![Word::new(0, 0.2, 0.5), Word::new(1, 0.6, 0.5)];
        let img2 = vec![Word::new(0, 0.7, 0.8), Word::new(1, 0.3, 0.3)];
        let m = LocationModel::build(&[img1, img2], &grid()).unwrap();
        let g = grid();
        assert_eq!(m.words(), &[0, 1]);
        // From A to B: B is 4 cells right (image 1), or 4 left and 4 up (image 2).
        assert!(m.consistent(0, 1, (4, 0), &g, 0));
        assert!(m.consistent(0, 1, (-4, -4), &g, 0));
        // From B to A: the mirror offsets.
        assert!(m.consistent(1, 0, (-4, 0), &g, 0));
        assert!(m.consistent(1, 0, (4, 4), &g, 0));
        // Unseen arrangement.
        assert!(!m.consistent(0, 1, (0, 3), &g, 0));
        assert!(m.consistent(0, 1, (3, 1), &g, 1));
    }

    #[test]
    fn repeated_words_store_both_orientations() {
        let img = vec![Word::new(5, 0.1, 0.1), Word::new(5, 0.5, 0.1)];
        let m = LocationModel::build(&[img], &grid()).unwrap();
        let g = grid();
        assert!(m.consistent(0, 0, (4, 0), &g, 0));
        assert!(m.consistent(0, 0, (-4, 0), &g, 0));
        assert_eq!(m.entries(), 2);
    }

    #[test]
    fn merging_adjacent_drives_adds_cross_pairs() {
        let day = vec![Word::new(1, 0.1, 0.5)];
        let night = vec![Word::new(2, 0.6, 0.5)];
        let mut merged = LocationMap::new(grid(), 0, true);
        let mut plain = LocationMap::new(grid(), 0, false);
        for map in [&mut merged, &mut plain] {
            map.add_drive(DriveRecord {
                time: 14.0,
                images: vec![(0, day.clone())],
            })
            .unwrap();
            map.add_drive(DriveRecord {
                time: 22.0,
                images: vec![(0, night.clone())],
            })
            .unwrap();
        }
        let g = grid();
        let (m, p) = (merged.model(0), plain.model(0));
        assert!(m.consistent(0, 1, (6, 0), &g, 0));
        assert!(!p.consistent(0, 1, (6, 0), &g, 0));
        assert_eq!(merged.postings(2), &[(0, 1)]);
    }

    #[test]
    fn only_drives_adjacent_in_time_are_merged() {
        let at = |w: u32, x: f32| vec![Word::new(w, x, 0.5)];
        let mut map = LocationMap::new(grid(), 0, true);
        // Added out of order: times 20, 10, 15 -> order 10 (word 1), 15 (word 2), 20 (word 3).
        for (t, w, x) in [(20.0, 3, 0.9), (10.0, 1, 0.1), (15.0, 2, 0.5)] {
            map.add_drive(DriveRecord {
                time: t,
                images: vec![(0, at(w, x))],
            })
            .unwrap();
        }
        let times: Vec<f64> = map.drives().iter().map(|d| d.time).collect();
        assert_eq!(times, vec![10.0, 15.0, 20.0]);
        let (g, m) = (grid(), map.model(0));
        assert!(m.consistent(0, 1, (4, 0), &g, 0)); // 10h with 15h
        assert!(m.consistent(1, 2, (4, 0), &g, 0)); // 15h with 20h
        assert!(!m.consistent(0, 2, (9, 0), &g, 0)); // 10h and 20h are not adjacent
    }

    #[test]
    fn new_locations_extend_the_route_and_index() {
        let mut map = LocationMap::new(grid(), 0, true);
        map.add_drive(DriveRecord {
            time: 0.0,
            images: vec![(3, vec![Word::new(7, 0.5, 0.5)])],
        })
        .unwrap();
        assert_eq!(map.locations(), 4);
        assert_eq!(map.postings(7), &[(3, 0)]);
        assert!(map.postings(8).is_empty());
        let err = map
            .add_drive(DriveRecord {
                time: f64::NAN,
                images: vec![],
            })
            .unwrap_err();
        assert!(err.to_string().contains("time"), "{err}");
    }

    #[test]
    fn positions_round_trip_within_fixed_point_precision() {
        let w = Word::new(1, 0.25, 0.999_999);
        let (x, y) = w.pos();
        assert!((x - 0.25).abs() < 1e-4 && y < 1.0);
    }
}
