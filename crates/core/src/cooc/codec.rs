//! A compact, versioned binary encoding of a [`CoocMap`] (for the service's store), without
//! serde: little-endian fields behind a magic and a version number.
//!
//! What is stored: the parameters, the vocabulary tree and, per drive, its time and the quantised
//! features of each image (8 bytes per feature). The location models and the inverted index are
//! *derived* data and are rebuilt on decoding, which keeps the encoding small (a model holds
//! `O(features^2)` pairs) and guarantees that a decoded map is consistent by construction.
//!
//! Layout v1: `b"SLCOOCMP"`, `u16` version, parameters, vocabulary (`dim`, `nodes`, `words`,
//! per node `first_child, child_count, leaf_word`, then `nodes * dim` `f32` centroids), drives
//! (`count`, per drive `f64 time`, `count`, per image `u32 location`, `u32 n`, `n` x
//! `(u32 word, u16 x, u16 y)`).
//!
//! Layout v2 (the current `VERSION`): v1 with two more keypoint parameters, `u32 max_width`
//! and `u32 octaves`, after `cell_size`. A map whose keypoints were extracted the v1 way (no
//! width cap, one octave) is still written as v1, so stored maps re-encode byte for byte; the
//! default parameters (`max_width` 640) are written as v2.
//!
//! Invariant: `decode(encode(m)) == m`; decoding never panics on arbitrary bytes and names what
//! is wrong.

use std::path::PathBuf;

use super::keypoints::KeypointParams;
use super::map::CoocMap;
use super::model::{DriveRecord, LocationMap, Word};
use super::vocabulary::Vocabulary;
use super::CoocParams;
use crate::codec::{ByteReader, ByteWriter, DecodeError};
use crate::{Error, Result};

const MAGIC: &[u8; 8] = b"SLCOOCMP";
const VERSION: u16 = 2;

fn corrupt(reason: impl Into<String>) -> Error {
    Error::Format {
        path: PathBuf::from("<co-occurrence map bytes>"),
        reason: reason.into(),
    }
}

/// The crate's byte codec; every error says what was being read and where.
struct Reader<'a>(ByteReader<'a>);

impl Reader<'_> {
    fn check<T>(&self, read: std::result::Result<T, DecodeError>, what: &str) -> Result<T> {
        read.map_err(|e| match e {
            DecodeError::Truncated { at } => {
                corrupt(format!("truncated at byte {at} while reading {what}"))
            }
            DecodeError::BadTag { .. } => corrupt(format!("{e} while reading {what}")),
        })
    }
    fn take<const N: usize>(&mut self, what: &str) -> Result<[u8; N]> {
        let read = self.0.array::<N>();
        self.check(read, what)
    }
    fn u8(&mut self, what: &str) -> Result<u8> {
        let read = self.0.u8();
        self.check(read, what)
    }
    fn u16(&mut self, what: &str) -> Result<u16> {
        let read = self.0.u16();
        self.check(read, what)
    }
    fn u32(&mut self, what: &str) -> Result<u32> {
        let read = self.0.u32();
        self.check(read, what)
    }
    fn u64(&mut self, what: &str) -> Result<u64> {
        let read = self.0.u64();
        self.check(read, what)
    }
    fn f32(&mut self, what: &str) -> Result<f32> {
        let read = self.0.f32();
        self.check(read, what)
    }
    fn f64(&mut self, what: &str) -> Result<f64> {
        let read = self.0.f64();
        self.check(read, what)
    }
    /// A count of items of at least `item_bytes` each, checked against the remaining bytes so a
    /// corrupt count cannot trigger a huge allocation.
    fn count(&mut self, what: &str, item_bytes: usize) -> Result<usize> {
        let n = self.u32(what)? as usize;
        if n.saturating_mul(item_bytes) > self.0.remaining() {
            return Err(corrupt(format!("{what} = {n} exceeds the remaining bytes")));
        }
        Ok(n)
    }
}

impl CoocMap {
    /// Encodes the map (see the module docs of `cooc::codec` for the layout).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut w = ByteWriter::new();
        w.raw(MAGIC);
        let p = &self.params;
        let k = &p.keypoints;
        // The oldest layout that holds the map: a map extracted the version-1 way (no width
        // cap, one octave) is written as version 1, so stored maps re-encode byte for byte.
        let version = if k.max_width == 0 && k.octaves == 1 {
            1
        } else {
            VERSION
        };
        w.u16(version);
        w.u32(k.upsample);
        w.count(k.max_keypoints);
        w.f32(k.harris_k);
        w.f32(k.relative_threshold);
        w.f32(k.min_response);
        w.u32(k.nms_radius);
        w.u32(k.cell_size);
        if version >= 2 {
            w.u32(k.max_width);
            w.u32(k.octaves);
        }
        w.count(p.vocabulary_branching);
        w.count(p.vocabulary_depth);
        w.count(p.kmeans_iterations);
        w.count(p.max_training_descriptors);
        w.u16(p.grid_cols);
        w.u16(p.grid_rows);
        w.u16(p.spatial_tolerance);
        w.u8(u8::from(p.merge_adjacent_drives));
        w.u64(p.seed);
        let v = &self.vocabulary;
        w.count(v.dim);
        w.count(v.children.len());
        w.u32(v.words);
        for (i, &(first, count)) in v.children.iter().enumerate() {
            w.u32(first);
            w.u32(count);
            w.u32(v.leaf_word[i]);
        }
        for &c in &v.centroids {
            w.f32(c);
        }
        let drives = self.locations.drives();
        w.count(drives.len());
        for d in drives {
            w.f64(d.time);
            w.count(d.images.len());
            for (loc, feats) in &d.images {
                w.u32(*loc);
                w.count(feats.len());
                for f in feats {
                    w.u32(f.word);
                    w.u16(f.x);
                    w.u16(f.y);
                }
            }
        }
        w.into_bytes()
    }

    /// Decodes bytes written by [`CoocMap::to_bytes`], rebuilding the models and the index.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        let mut r = Reader(ByteReader::new(bytes));
        if r.take::<8>("magic")? != *MAGIC {
            return Err(corrupt("not a co-occurrence map (bad magic)"));
        }
        let version = r.u16("version")?;
        if !(1..=VERSION).contains(&version) {
            return Err(corrupt(format!(
                "unsupported version {version} (this build reads 1..={VERSION})"
            )));
        }
        let mut keypoints = KeypointParams {
            upsample: r.u32("upsample")?,
            max_keypoints: r.u32("max_keypoints")? as usize,
            harris_k: r.f32("harris_k")?,
            relative_threshold: r.f32("relative_threshold")?,
            min_response: r.f32("min_response")?,
            nms_radius: r.u32("nms_radius")?,
            cell_size: r.u32("cell_size")?,
            // Version 1 maps were extracted without a width cap, on one octave: decoding keeps
            // that, so their queries are described exactly as their drives were.
            max_width: 0,
            octaves: 1,
        };
        if version >= 2 {
            keypoints.max_width = r.u32("max_width")?;
            keypoints.octaves = r.u32("octaves")?;
        }
        let params = CoocParams {
            keypoints,
            vocabulary_branching: r.u32("vocabulary_branching")? as usize,
            vocabulary_depth: r.u32("vocabulary_depth")? as usize,
            kmeans_iterations: r.u32("kmeans_iterations")? as usize,
            max_training_descriptors: r.u32("max_training_descriptors")? as usize,
            grid_cols: r.u16("grid_cols")?,
            grid_rows: r.u16("grid_rows")?,
            spatial_tolerance: r.u16("spatial_tolerance")?,
            merge_adjacent_drives: r.u8("merge_adjacent_drives")? != 0,
            seed: r.u64("seed")?,
        };
        params.validate()?;
        let dim = r.u32("vocabulary dim")? as usize;
        if dim != super::keypoints::DESCRIPTOR_DIM {
            return Err(corrupt(format!("vocabulary dimension {dim}, expected 128")));
        }
        let nodes = r.count("vocabulary nodes", 12 + 4 * dim)?;
        let words = r.u32("vocabulary words")?;
        let mut children = Vec::with_capacity(nodes);
        let mut leaf_word = Vec::with_capacity(nodes);
        for _ in 0..nodes {
            children.push((r.u32("child index")?, r.u32("child count")?));
            leaf_word.push(r.u32("leaf word")?);
        }
        let mut centroids = Vec::with_capacity(nodes * dim);
        for _ in 0..nodes * dim {
            centroids.push(r.f32("centroid")?);
        }
        let vocabulary = Vocabulary {
            dim,
            centroids,
            children,
            leaf_word,
            words,
        };
        vocabulary.check().map_err(|e| corrupt(e.to_string()))?;
        let mut locations = LocationMap::new(
            params.grid()?,
            params.spatial_tolerance,
            params.merge_adjacent_drives,
        );
        let n_drives = r.count("drive count", 12)?;
        for d in 0..n_drives {
            let time = r.f64("drive time")?;
            let n_images = r.count("image count", 8)?;
            let mut images = Vec::with_capacity(n_images);
            for _ in 0..n_images {
                let loc = r.u32("location")?;
                let n = r.count("feature count", 8)?;
                let mut feats = Vec::with_capacity(n);
                for _ in 0..n {
                    let f = Word {
                        word: r.u32("word")?,
                        x: r.u16("x")?,
                        y: r.u16("y")?,
                    };
                    if f.word >= words {
                        return Err(corrupt(format!(
                            "drive {d}: word {} outside the {words}-word vocabulary",
                            f.word
                        )));
                    }
                    feats.push(f);
                }
                images.push((loc, feats));
            }
            locations
                .add_drive(DriveRecord { time, images })
                .map_err(|e| corrupt(format!("drive {d}: {e}")))?;
        }
        if r.0.remaining() != 0 {
            return Err(corrupt(format!("{} trailing bytes", r.0.remaining())));
        }
        Ok(CoocMap {
            params,
            vocabulary,
            locations,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::super::map::tests::scene;
    use super::super::map::Drive;
    use super::*;

    fn small_map() -> CoocMap {
        let p = CoocParams {
            vocabulary_branching: 6,
            vocabulary_depth: 2,
            ..CoocParams::default()
        };
        let day = (0..6).map(|s| scene(s, false)).collect();
        let night = (0..6).map(|s| scene(s, true)).collect();
        CoocMap::build(
            &p,
            &[
                Drive::sequential(9.0, day).unwrap(),
                Drive::sequential(21.0, night).unwrap(),
            ],
        )
        .unwrap()
    }

    #[test]
    fn round_trips_exactly() {
        let m = small_map();
        let bytes = m.to_bytes();
        let back = CoocMap::from_bytes(&bytes).unwrap();
        assert_eq!(back, m);
        assert_eq!(back.to_bytes(), bytes);
    }

    #[test]
    fn rejects_corruption_with_a_reason() {
        let bytes = small_map().to_bytes();
        let err = CoocMap::from_bytes(b"PNG").unwrap_err().to_string();
        assert!(err.contains("truncated"), "{err}");
        let mut bad = bytes.clone();
        bad[0] = b'X';
        assert!(CoocMap::from_bytes(&bad)
            .unwrap_err()
            .to_string()
            .contains("magic"));
        let mut bad = bytes.clone();
        bad[8] = 9;
        assert!(CoocMap::from_bytes(&bad)
            .unwrap_err()
            .to_string()
            .contains("version 9"));
        let err = CoocMap::from_bytes(&bytes[..bytes.len() - 3])
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("truncated") || err.contains("exceeds the remaining"),
            "{err}"
        );
        let mut long = bytes.clone();
        long.push(0);
        assert!(CoocMap::from_bytes(&long)
            .unwrap_err()
            .to_string()
            .contains("trailing"));
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]
        #[test]
        fn never_panics_on_flipped_bytes(pos in 0usize..1_000_000, val in 0u8..=255) {
            static BYTES: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
            let mut bytes = BYTES.get_or_init(|| small_map().to_bytes()).clone();
            let p = pos % bytes.len();
            bytes[p] = val;
            let _ = CoocMap::from_bytes(&bytes);
        }
    }
}
