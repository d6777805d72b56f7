//! The data and the derivations: a map (reference descriptors of places `0..map_len`), a pool
//! of query frames (frame `f < map_len` shows place `f`, frames from `map_len` on are off the
//! map) and query drives as lists of pool frames.

use seasonloc_core::features::hog::{HogOptions, HogSpec};
use seasonloc_core::features::{extract_files, image_file_size, Fit, Fitted};
use seasonloc_core::Matrix;

/// Places of the Gardens Point map (day_right frames `0..GP_MAP`).
const GP_MAP: usize = 70;
/// First night frame of the Gardens Point detour (16 places past the map's last, 69).
const GP_OFF_MAP: usize = 85;

/// A map and a pool of query frames.
pub struct Data {
    pub name: &'static str,
    pub references: Matrix,
    pool: Matrix,
    pub map_len: usize,
    /// Scoring tolerance in frames.
    pub tolerance: usize,
    /// Where the derived sections start and how long they are.
    start: usize,
    len: usize,
    /// First pool frame of the off-map stretch used by the detour.
    off_map: usize,
    /// Fraction of rows that must be right (or hidden, for a detour).
    min_fraction: f64,
}

/// What a case must show.
pub enum Expectation {
    /// Each named part of the drive is localized within the tolerance.
    Localized {
        parts: Vec<(&'static str, Vec<usize>)>,
        min_fraction: f64,
    },
    /// The detour rows are hidden (the on-map rows: `detour` in `main.rs`).
    Detour {
        on_map: Vec<usize>,
        off_map: Vec<usize>,
        min_fraction: f64,
    },
}

/// One derived drive.
pub struct Case {
    pub name: &'static str,
    /// Pool frames in driving order.
    pub frames: Vec<usize>,
    /// The true map place of each row (`None` off the map).
    pub truth: Vec<Option<usize>>,
    pub expect: Expectation,
}

impl Case {
    fn new(data: &Data, name: &'static str, frames: Vec<usize>, expect: Expectation) -> Self {
        let truth = frames
            .iter()
            .map(|&f| (f < data.map_len).then_some(f))
            .collect();
        Case {
            name,
            frames,
            truth,
            expect,
        }
    }

    /// The same case with another required fraction (0: print only).
    pub fn with_min_fraction(&self, f: f64) -> Case {
        let expect = match &self.expect {
            Expectation::Localized { parts, .. } => Expectation::Localized {
                parts: parts.clone(),
                min_fraction: f,
            },
            Expectation::Detour {
                on_map, off_map, ..
            } => Expectation::Detour {
                on_map: on_map.clone(),
                off_map: off_map.clone(),
                min_fraction: f,
            },
        };
        Case {
            name: self.name,
            frames: self.frames.clone(),
            truth: self.truth.clone(),
            expect,
        }
    }
}

/// A deterministic generator (SplitMix64) of values in `[-1, 1)`.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 40) as f32 / (1u64 << 23) as f32 - 1.0
    }
}

impl Data {
    /// A generated route of 150 places (64-D non-negative descriptors that change smoothly
    /// along the route, as consecutive frames do) seen in two "seasons" (independent noise),
    /// and 40 off-map frames.
    pub fn generated() -> Data {
        let (map_len, extra, dim) = (150, 40, 64);
        let mut rng = Rng(14);
        let mut place = vec![0.0f32; dim];
        let mut places = Vec::new();
        for _ in 0..map_len + extra {
            for v in place.iter_mut() {
                *v = 0.5 * *v + rng.next();
            }
            places.push(place.clone());
        }
        // Non-negative like HOG or CNN activations: an offset, the season's noise, clamped.
        let season = |rng: &mut Rng, p: &[f32]| -> Vec<f32> {
            p.iter()
                .map(|&v| (1.5 + v + 0.6 * rng.next()).max(0.0))
                .collect()
        };
        let refs: Vec<Vec<f32>> = places[..map_len]
            .iter()
            .map(|p| season(&mut rng, p))
            .collect();
        let pool: Vec<Vec<f32>> = places.iter().map(|p| season(&mut rng, p)).collect();
        Data {
            name: "generated",
            references: Matrix::from_rows(&refs).unwrap(),
            pool: Matrix::from_rows(&pool).unwrap(),
            map_len,
            tolerance: 1,
            start: 30,
            len: 60,
            off_map: map_len,
            min_fraction: 0.9,
        }
    }

    /// Nordland dev: the map is summer frames 0..1200, the pool all 2400 winter frames (those
    /// from 1200 on are off the map). `None` (with a message) when the data is absent.
    pub fn nordland() -> Option<Data> {
        let dir = crate::nordland::nordland()?;
        let files = |season: &str| crate::nordland::nordland_files(&dir.join(season));
        let spec = HogSpec::new(HogOptions {
            cell_size: 8,
            resize: None,
        })
        .unwrap();
        let map_len = 1200;
        let references = extract_files(&spec, &files("summer")[..map_len], &|| {}).unwrap();
        let pool = extract_files(&spec, &files("winter"), &|| {}).unwrap();
        Some(Data {
            name: "nordland",
            references,
            pool,
            map_len,
            tolerance: 1,
            start: 300,
            len: 200,
            off_map: 1800,
            min_fraction: 0.7,
        })
    }

    /// Gardens Point dev: the map is the day walk on the right of the path, frames
    /// `0..GP_MAP`, the pool all 100 night frames (640x360, brought to the map's 960x540 by the
    /// shipped stretch); night frames from [`GP_OFF_MAP`] on show places 16 or more steps past
    /// the map's last, so they are off the map. HOG with the shipped 32 px cells, tolerance 2
    /// (the dataset's README). `None` (with a message) when the data is absent.
    pub fn gardens_point() -> Option<Data> {
        let dir = crate::gardens_point::gardens_point()?;
        let day = crate::gardens_point::traversal(&dir, "day_right");
        let night = crate::gardens_point::traversal(&dir, "night_right");
        let geometry = image_file_size(&day[0]).unwrap();
        let hog = Fitted::hog(32, geometry, Fit::Stretch).unwrap();
        let references = extract_files(&hog, &day[..GP_MAP], &|| {}).unwrap();
        let pool = extract_files(&hog, &night, &|| {}).unwrap();
        Some(Data {
            name: "gardens point",
            references,
            pool,
            map_len: GP_MAP,
            tolerance: 2,
            start: 10,
            len: 40,
            off_map: GP_OFF_MAP,
            min_fraction: 0.7,
        })
    }

    /// The query descriptors of a drive.
    pub fn queries(&self, frames: &[usize]) -> Matrix {
        let rows: Vec<&[f32]> = frames.iter().map(|&f| self.pool.row(f)).collect();
        Matrix::from_rows(&rows).unwrap()
    }
}

/// The section `start .. start + len` driven twice.
pub fn loop_case(data: &Data) -> Case {
    let pass: Vec<usize> = (data.start..data.start + data.len).collect();
    let frames = [pass.clone(), pass].concat();
    let n = data.len;
    Case::new(
        data,
        "loop",
        frames,
        Expectation::Localized {
            parts: vec![
                ("first pass", (0..n).collect()),
                ("second pass", (n..2 * n).collect()),
            ],
            min_fraction: data.min_fraction,
        },
    )
}

/// Every 2nd frame, every 3rd frame, and stops (each frame held for 1 to 4 frames).
pub fn speed_cases(data: &Data) -> Vec<Case> {
    let (s, n) = (data.start, data.len);
    let all = |frames: &[usize]| -> Vec<(&'static str, Vec<usize>)> {
        vec![("all rows", (0..frames.len()).collect())]
    };
    let mut cases = Vec::new();
    for (name, step) in [("every 2nd frame", 2), ("every 3rd frame", 3)] {
        let frames: Vec<usize> = (s..s + n).step_by(step).collect();
        let parts = all(&frames);
        cases.push(Case::new(
            data,
            name,
            frames,
            Expectation::Localized {
                parts,
                min_fraction: data.min_fraction,
            },
        ));
    }
    let frames: Vec<usize> = (s..s + n)
        .flat_map(|f| std::iter::repeat_n(f, 1 + (f * 7) % 4))
        .collect();
    let parts = all(&frames);
    cases.push(Case::new(
        data,
        "stops",
        frames,
        Expectation::Localized {
            parts,
            min_fraction: data.min_fraction,
        },
    ));
    cases
}

/// `len/2` frames on the map, `len/4` frames off it, then back on the map `len/4` places
/// further on (the part the detour bypassed), for `len/2` frames.
pub fn detour_case(data: &Data) -> Case {
    let (s, h, q) = (data.start, data.len / 2, data.len / 4);
    let before: Vec<usize> = (s..s + h).collect();
    let off: Vec<usize> = (data.off_map..data.off_map + q).collect();
    let after: Vec<usize> = (s + h + q..s + 2 * h + q).collect();
    let frames = [before, off, after].concat();
    let on_map = (0..h).chain(h + q..2 * h + q).collect();
    let off_map = (h..h + q).collect();
    Case::new(
        data,
        "detour",
        frames,
        Expectation::Detour {
            on_map,
            off_map,
            min_fraction: data.min_fraction,
        },
    )
}

/// The drive of [`detour_case`] with the bypassed places driven instead of the detour: the
/// same frames on the map, and the section the detour left out in between.
pub fn straight_case(data: &Data) -> Case {
    let (s, h, q) = (data.start, data.len / 2, data.len / 4);
    let frames: Vec<usize> = (s..s + 2 * h + q).collect();
    Case::new(
        data,
        "detour's section driven straight",
        frames,
        Expectation::Localized {
            parts: vec![
                (
                    "the detour drive's on-map rows",
                    (0..h).chain(h + q..2 * h + q).collect(),
                ),
                ("the bypassed places", (h..h + q).collect()),
            ],
            min_fraction: 0.0,
        },
    )
}
