//! Location models (Section II-B) and the map of all locations with its inverted index.
//!
//! A word-co-occurrence matrix `M` has one row per visual word seen (a lookup table maps rows
//! to words) and, for each word pair, the *set* of spatial words in which the pair was
//! observed. It is stored sparsely: `words` (sorted, row `r` is `words[r]`), and per row `a` a
//! sorted run of packed `(row_b, spatial word)` entries with `row_a <= row_b` and the spatial
//! word oriented from `a` to `b` (for `row_a == row_b` both orientations are stored), so a
//! lookup is one short binary search inside a row and the matrix takes 4 bytes per entry. The
//! spatial word is stored as the signed cell offset it stands for (`dx`, `dy`, one byte each),
//! so the consistency test on the recognition path is two subtractions, not a division.
//!
//! **One model per training image.** The paper scores a location by "groups of features in the
//! query image that have all co-occurred together in one of the training images for this
//! location" (II-C). A location therefore keeps one model per training image ("set"): each
//! drive's image of it and, with interpolation on, every *virtual* image of Section II-E (the
//! union of the images of two drives adjacent in time). Its score is the best group over its
//! sets. Fusing every image into a single matrix instead lets a group mix pairs seen in
//! different images; measured on Gardens Point (`docs/cooc.md`), that raised the scores of
//! wrong locations with every drive added, so fusing a night drive made day queries *worse*.
//! With one model per set, a further drive adds sets and a location can only gain matches.
//!
//! Interpolation merges only drives at *different* times (sorted by time; drives at equal
//! times are the same time of day and have nothing to interpolate between).
//!
//! [`LocationMap`] keeps, per mapping drive, the quantised features it saw at each location, and
//! derives the models from them. Sets are numbered map-wide location by location ("entities"),
//! so the search can treat them as independent candidates and report their location.
//!
//! Invariants: `sets(l)` holds every set of location `l`; entities are numbered in location
//! order; the inverted index lists `(entity, row)` for exactly the words in each model, by
//! entity; drives are kept in time order (stable for equal times).

use rayon::prelude::*;

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

/// Most distinct words one training set (image or virtual image) may have.
const MAX_ROWS: usize = 1 << 16;

/// The word-co-occurrence matrix `M` of one training set of a location.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LocationModel {
    words: Vec<u32>,
    /// `row_start[a]..row_start[a + 1]` are row `a`'s entries in `pairs`.
    row_start: Vec<u32>,
    /// `(row_b << 16) | (dx as u8) << 8 | (dy as u8)`: the spatial word as its signed cell
    /// offset; sorted within each row.
    pairs: Vec<u32>,
}

impl LocationModel {
    /// Builds `M` from "images" (feature sets): every pair within one set is recorded.
    pub fn build(sets: &[Vec<Word>], grid: &SpatialGrid) -> Result<Self> {
        let mut words: Vec<u32> = sets.iter().flatten().map(|f| f.word).collect();
        words.sort_unstable();
        words.dedup();
        if words.len() > MAX_ROWS {
            return Err(Error::Shape(format!(
                "a training image has {} distinct words, more than {MAX_ROWS}",
                words.len()
            )));
        }
        let row = |w: u32| words.partition_point(|&x| x < w) as u64;
        let pack = |a: u64, b: u64, s: u16| {
            let (dx, dy) = grid.offset(s);
            (a << 32) | (b << 16) | u64::from(dx as u8) << 8 | u64::from(dy as u8)
        };
        let total: usize = sets.iter().map(|s| s.len() * s.len()).sum();
        let mut packed = Vec::with_capacity(total / 2 + 1);
        let mut rows = Vec::new();
        for set in sets {
            rows.clear();
            rows.extend(set.iter().map(|f| row(f.word)));
            for i in 0..set.len() {
                for j in i + 1..set.len() {
                    let (pi, pj) = (set[i].pos(), set[j].pos());
                    let (ri, rj) = (rows[i], rows[j]);
                    if ri < rj {
                        packed.push(pack(ri, rj, grid.word(pi, pj)));
                    } else if rj < ri {
                        packed.push(pack(rj, ri, grid.word(pj, pi)));
                    } else {
                        packed.push(pack(ri, rj, grid.word(pi, pj)));
                        packed.push(pack(ri, rj, grid.word(pj, pi)));
                    }
                }
            }
        }
        packed.sort_unstable();
        packed.dedup();
        let mut row_start = vec![0u32; words.len() + 1];
        for &p in &packed {
            row_start[(p >> 32) as usize + 1] += 1;
        }
        for r in 0..words.len() {
            row_start[r + 1] += row_start[r];
        }
        let pairs = packed.iter().map(|&p| p as u32).collect();
        Ok(LocationModel {
            words,
            row_start,
            pairs,
        })
    }

    /// The visual words with a row in `M`, sorted (row `r` is `words()[r]`).
    pub fn words(&self) -> &[u32] {
        &self.words
    }

    /// Number of distinct `(word pair, signed cell offset)` entries.
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
    pub fn consistent(&self, a: u32, b: u32, observed: (i16, i16), tolerance: u16) -> bool {
        let (lo, hi, obs) = if a <= b {
            (a, b, observed)
        } else {
            (b, a, (-observed.0, -observed.1))
        };
        let run = self.run(lo);
        let start = hi << 16;
        let first = run.partition_point(|&p| p < start);
        run[first..]
            .iter()
            .take_while(|&&p| p >> 16 == hi)
            .any(|&p| entry_matches(p, obs, tolerance as i16))
    }

    /// Row `a`'s packed entries (`row_b >= a`), sorted by `row_b` (see [`LocationModel`]).
    #[inline]
    pub(crate) fn run(&self, a: u32) -> &[u32] {
        &self.pairs[self.row_start[a as usize] as usize..self.row_start[a as usize + 1] as usize]
    }
}

/// Whether a packed entry's cell offset is within `tolerance` of `observed` on both axes.
#[inline]
pub(crate) fn entry_matches(entry: u32, observed: (i16, i16), tolerance: i16) -> bool {
    let dx = i16::from((entry >> 8) as u8 as i8);
    let dy = i16::from(entry as u8 as i8);
    (dx - observed.0).abs() <= tolerance && (dy - observed.1).abs() <= tolerance
}

/// One location's training-set models and, per set, its time and whether it is virtual.
type LocationSets = (Vec<LocationModel>, Vec<(f64, bool)>);

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
    /// Per location, the models of its training sets.
    models: Vec<Vec<LocationModel>>,
    /// Per location, the time of each training set (for a virtual image: the earlier of its
    /// two times) and whether it is virtual; [`LocationMap::sources`] are derived from them.
    set_times: Vec<Vec<(f64, bool)>>,
    /// The source of every entity (see [`LocationMap::entity_source`]).
    entity_source: Vec<u32>,
    /// Number of sources.
    sources: usize,
    /// `first_entity[l]..first_entity[l + 1]` are location `l`'s entities (one per set).
    first_entity: Vec<u32>,
    /// The location of every entity.
    entity_location: Vec<u32>,
    /// `index[w]` = `(entity, row)` of every set model that has word `w`, by entity.
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
            set_times: Vec::new(),
            entity_source: Vec::new(),
            sources: 0,
            first_entity: vec![0],
            entity_location: Vec::new(),
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
            self.models.resize(needed, Vec::new());
            self.set_times.resize(needed, Vec::new());
        }
        let rebuilt: Vec<LocationSets> = touched
            .par_iter()
            .map(|&loc| self.build_sets(loc))
            .collect::<Result<_>>()?;
        for (&loc, (sets, times)) in touched.iter().zip(rebuilt) {
            self.models[loc as usize] = sets;
            self.set_times[loc as usize] = times;
        }
        self.rebuild_index();
        Ok(())
    }

    /// The training sets of one location: every image of it, then (interpolation on) the
    /// union of every two images of drives adjacent in time (Section II-E); each with its time
    /// (a virtual image: the earlier one) and whether it is virtual.
    fn training_sets(&self, loc: u32) -> Vec<(f64, bool, Vec<Word>)> {
        // Per distinct time, in time order: the images of that time at `loc`.
        let mut per_time: Vec<(f64, Vec<&Vec<Word>>)> = Vec::new();
        for d in &self.drives {
            let here = d.images.iter().filter(|(l, _)| *l == loc).map(|(_, f)| f);
            match per_time.last_mut() {
                Some((t, v)) if *t == d.time => v.extend(here),
                _ => per_time.push((d.time, here.collect())),
            }
        }
        per_time.retain(|(_, v)| !v.is_empty());
        let mut sets: Vec<(f64, bool, Vec<Word>)> = per_time
            .iter()
            .flat_map(|(t, v)| v.iter().map(|f| (*t, false, (*f).clone())))
            .collect();
        if self.merge_adjacent {
            for pair in per_time.windows(2) {
                for a in &pair[0].1 {
                    for b in &pair[1].1 {
                        let union = a.iter().chain(b.iter()).copied().collect();
                        sets.push((pair[0].0, true, union));
                    }
                }
            }
        }
        sets
    }

    fn build_sets(&self, loc: u32) -> Result<LocationSets> {
        let sets = self.training_sets(loc);
        let models = sets
            .iter()
            .map(|(_, _, set)| LocationModel::build(std::slice::from_ref(set), &self.grid))
            .collect::<Result<_>>()?;
        Ok((models, sets.iter().map(|&(t, v, _)| (t, v)).collect()))
    }

    fn rebuild_index(&mut self) {
        let top = self
            .models
            .iter()
            .flatten()
            .filter_map(|m| m.words.last())
            .max()
            .map_or(0, |&w| w as usize + 1);
        let mut index: Vec<Vec<(u32, u32)>> = vec![Vec::new(); top];
        let mut first_entity = Vec::with_capacity(self.models.len() + 1);
        let mut entity_location = Vec::new();
        first_entity.push(0u32);
        for (loc, sets) in self.models.iter().enumerate() {
            for m in sets {
                let e = entity_location.len() as u32;
                entity_location.push(loc as u32);
                for (row, &w) in m.words.iter().enumerate() {
                    index[w as usize].push((e, row as u32));
                }
            }
            first_entity.push(entity_location.len() as u32);
        }
        self.index = index;
        self.first_entity = first_entity;
        self.entity_location = entity_location;
        // Sources: the distinct drive times in order, then one per virtual time pair.
        let mut times: Vec<f64> = self.drives.iter().map(|d| d.time).collect();
        times.dedup();
        let slot = |t: f64| times.partition_point(|&x| x < t) as u32;
        self.entity_source = self
            .set_times
            .iter()
            .flatten()
            .map(|&(t, v)| slot(t) + if v { times.len() as u32 } else { 0 })
            .collect();
        self.sources = times.len()
            + if self.merge_adjacent {
                times.len().saturating_sub(1)
            } else {
                0
            };
    }

    /// Number of locations.
    pub fn locations(&self) -> usize {
        self.models.len()
    }

    /// The models of the training sets of location `loc`.
    pub fn sets(&self, loc: usize) -> &[LocationModel] {
        &self.models[loc]
    }

    /// Number of entities (training sets over all locations).
    pub fn entities(&self) -> usize {
        self.entity_location.len()
    }

    /// Number of sources: one per distinct drive time (drives at the same time are one
    /// appearance), in time order, then (interpolation on) one per pair of adjacent times for
    /// the virtual images. A location's score from one source is comparable across locations;
    /// sources differ in their chance level (`docs/cooc.md`).
    pub fn sources(&self) -> usize {
        self.sources
    }

    /// Which locations each source has a training set of: `sources() x locations()`,
    /// source-major. A location without any training set counts as source 0's (its score is 0
    /// everywhere, as in the maximum over sources).
    pub fn source_present(&self) -> Vec<bool> {
        let l = self.locations();
        let mut present = vec![false; self.sources.max(1) * l];
        for (e, &loc) in self.entity_location.iter().enumerate() {
            present[self.entity_source[e] as usize * l + loc as usize] = true;
        }
        for (loc, sets) in self.models.iter().enumerate() {
            if sets.is_empty() {
                present[loc] = true;
            }
        }
        present
    }

    /// The source of entity `e`, `< sources()`.
    #[inline]
    pub fn entity_source(&self, e: u32) -> usize {
        self.entity_source[e as usize] as usize
    }

    /// The location of entity `e`.
    #[inline]
    pub fn entity_location(&self, e: u32) -> usize {
        self.entity_location[e as usize] as usize
    }

    /// The model of entity `e`.
    #[inline]
    pub fn entity_model(&self, e: u32) -> &LocationModel {
        let loc = self.entity_location(e);
        &self.models[loc][(e - self.first_entity[loc]) as usize]
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

    /// Postings of visual word `w`: `(entity, row)`, by entity.
    pub fn postings(&self, w: u32) -> &[(u32, u32)] {
        self.index.get(w as usize).map_or(&[], |v| v.as_slice())
    }

    /// Total `(word pair, spatial word)` entries over all models.
    pub fn entries(&self) -> usize {
        self.models.iter().flatten().map(|m| m.entries()).sum()
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
        assert_eq!(m.words(), &[0, 1]);
        // From A to B: B is 4 cells right (image 1), or 4 left and 4 up (image 2).
        assert!(m.consistent(0, 1, (4, 0), 0));
        assert!(m.consistent(0, 1, (-4, -4), 0));
        // From B to A: the mirror offsets.
        assert!(m.consistent(1, 0, (-4, 0), 0));
        assert!(m.consistent(1, 0, (4, 4), 0));
        // Unseen arrangement.
        assert!(!m.consistent(0, 1, (0, 3), 0));
        assert!(m.consistent(0, 1, (3, 1), 1));
    }

    #[test]
    fn repeated_words_store_both_orientations() {
        let img = vec![Word::new(5, 0.1, 0.1), Word::new(5, 0.5, 0.1)];
        let m = LocationModel::build(&[img], &grid()).unwrap();
        assert!(m.consistent(0, 0, (4, 0), 0));
        assert!(m.consistent(0, 0, (-4, 0), 0));
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
        // Plain: one set per image; merged: also the virtual image day + night.
        assert_eq!(plain.sets(0).len(), 2);
        assert_eq!(merged.sets(0).len(), 3);
        let virtual_image = &merged.sets(0)[2];
        assert!(virtual_image.consistent(0, 1, (6, 0), 0));
        assert!(plain.sets(0).iter().all(|m| m.words().len() == 1));
        // Word 2 is in the night set (entity 1, row 0) and the virtual image (entity 2, row 1).
        assert_eq!(merged.postings(2), &[(1, 0), (2, 1)]);
        assert_eq!(merged.entity_location(2), 0);
    }

    #[test]
    fn drives_at_the_same_time_are_not_merged() {
        let mut map = LocationMap::new(grid(), 0, true);
        for (w, x) in [(1, 0.1), (2, 0.6)] {
            map.add_drive(DriveRecord {
                time: 12.0,
                images: vec![(0, vec![Word::new(w, x, 0.5)])],
            })
            .unwrap();
        }
        assert_eq!(map.sets(0).len(), 2);
        assert_eq!(map.entities(), 2);
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
        let sets = map.sets(0);
        // Three images, then the virtual images 10h+15h and 15h+20h; never 10h+20h.
        assert_eq!(sets.len(), 5);
        assert_eq!(sets[3].words(), &[1, 2]);
        assert!(sets[3].consistent(0, 1, (4, 0), 0)); // 10h with 15h
        assert_eq!(sets[4].words(), &[2, 3]);
        assert!(sets[4].consistent(0, 1, (4, 0), 0)); // 15h with 20h
        assert!(sets.iter().all(|m| m.words() != [1, 3]));
    }

    #[test]
    fn sources_are_drive_times_then_virtual_pairs() {
        let img = |w: u32| vec![Word::new(w, 0.2, 0.5), Word::new(w + 1, 0.6, 0.5)];
        for merge in [false, true] {
            let mut map = LocationMap::new(grid(), 0, merge);
            for (t, loc) in [(22.0, 0), (12.0, 0), (12.0, 1)] {
                map.add_drive(DriveRecord {
                    time: t,
                    images: vec![(loc, img(loc * 10))],
                })
                .unwrap();
            }
            // Times 12 (two drives: one appearance) and 22.
            let expected = if merge { 3 } else { 2 };
            assert_eq!(map.sources(), expected);
            let sources: Vec<usize> = (0..map.entities() as u32)
                .map(|e| map.entity_source(e))
                .collect();
            // Location 0: the 12 h image, the 22 h image (and their virtual image); location 1:
            // the 12 h image.
            let want = if merge {
                vec![0, 1, 2, 0]
            } else {
                vec![0, 1, 0]
            };
            assert_eq!(sources, want, "merge {merge}");
            let present = map.source_present();
            assert_eq!(&present[..4], &[true, true, true, false]);
            // A drive at an earlier time renumbers the sources of every location.
            map.add_drive(DriveRecord {
                time: 6.0,
                images: vec![(1, img(50))],
            })
            .unwrap();
            assert_eq!(map.sources(), if merge { 5 } else { 3 });
            assert_eq!(
                map.entity_source(0),
                1,
                "location 0's 12 h image is now source 1"
            );
        }
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
        assert_eq!(map.postings(7), &[(0, 0)]);
        assert_eq!(map.entity_location(0), 3);
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
