//! Feature co-occurrence maps (Johns & Yang, *Feature Co-occurrence Maps: Appearance-based
//! Localisation Throughout the Day*, ICRA 2013): the second localization method.
//!
//! A route is mapped by one or more drives. Every image is reduced to local features
//! ([`keypoints`]), each quantised to a visual word ([`vocabulary`]); every feature pair gets a
//! spatial word ([`spatial`]: the grid offset and the above/below/left/right relation). Per
//! location a word-co-occurrence model ([`model`]) records which word pairs were seen in which
//! spatial arrangement, over all drives, with drives adjacent in time merged (Section II-E).
//! A query is matched against all locations at once ([`recognition`]): an inverted index gives
//! candidate correspondences, the correspondence-consistency matrix is shrunk by iterative
//! elimination to a globally consistent group (II-C), and the maximum potential score bounds the
//! search (II-D). [`sequence`] adds the forward-only, variable-speed sequence matching (II-F);
//! [`CoocMap::score_matrix`] feeds the co-occurrence scores to the network-flow graph instead.
//! [`localize()`] (with [`CoocMethod`]) is the one entry point that runs any of the three methods,
//! shared by the CLI and the service.
//!
//! Invariants: a built [`CoocMap`] has a vocabulary, one model per location (possibly empty) and
//! an inverted index consistent with the models; every stage is deterministic for a given
//! [`CoocParams::seed`]. This module depends only on core modules (`crate::Error`,
//! `crate::Matrix`, `crate::codec` for its byte encoding, `crate::similarity` for the column
//! normalisation, `crate::solver` and `crate::localize` for `cooc-flow` and the shared
//! `Prediction`, SeqSLAM's contrast enhancement `crate::baselines::enhance_contrast`, an option
//! of the sequence matching), `image` and `rayon` (no serde, no I/O).

mod codec;
mod fusion;
pub mod keypoints;
mod localize;
mod map;
pub mod model;
pub mod recognition;
pub mod sequence;
pub mod spatial;
pub mod vocabulary;

pub use fusion::{
    check_sources, decisiveness, fuse_rows, fused_scores, fused_similarity, normalise_sources,
    off_peak_noise, off_peak_stats, rank_sources, row_peak, source_order, WHOLE_BATCH,
};
pub use localize::{best_per_query, localize, CoocMethod, CoocOptions, CoocQueries};
pub use map::{extract_all, flow_similarity, CoocMap, Drive, DriveFeatures};
pub use model::{LocationMap, Word};
pub use recognition::{Recognition, Schedule};
pub use sequence::SequenceParams;

use crate::{Error, Result};

/// Every parameter of the co-occurrence method. Check with [`CoocParams::validate`] (the map
/// builder does).
#[derive(Clone, Debug, PartialEq)]
pub struct CoocParams {
    /// Keypoint detection and description.
    pub keypoints: keypoints::KeypointParams,
    /// Branching factor `b` of the vocabulary tree (hierarchical k-means).
    pub vocabulary_branching: usize,
    /// Depth `L` of the vocabulary tree: at most `b^L` visual words.
    pub vocabulary_depth: usize,
    /// Lloyd iterations per k-means node.
    pub kmeans_iterations: usize,
    /// At most this many descriptors (sampled evenly) train the vocabulary.
    pub max_training_descriptors: usize,
    /// Spatial grid columns (the paper uses 12).
    pub grid_cols: u16,
    /// Spatial grid rows (the paper uses 8).
    pub grid_rows: u16,
    /// Two spatial words are consistent when their signed grid offsets differ by at most this
    /// many cells per axis (0 = the paper's exact equality).
    pub spatial_tolerance: u16,
    /// Merge the features of drives adjacent in time into "virtual" images (Section II-E).
    /// Off by default: it assumes drives close in appearance (the paper's tours were 1-2 h
    /// apart); where adjacent drives differ (viewpoint, day and night) a virtual image has up to
    /// twice the features of a real one and raises every wrong location's chance score, so
    /// fusing a drive made the map worse (`docs/cooc.md`, measured).
    pub merge_adjacent_drives: bool,
    /// Seed of every random choice (k-means initialisation, descriptor sampling).
    pub seed: u64,
}

impl Default for CoocParams {
    fn default() -> Self {
        CoocParams {
            keypoints: keypoints::KeypointParams::default(),
            vocabulary_branching: 32,
            vocabulary_depth: 2,
            kmeans_iterations: 8,
            max_training_descriptors: 40_000,
            grid_cols: 12,
            grid_rows: 8,
            spatial_tolerance: 1,
            merge_adjacent_drives: false,
            seed: 0x5ea5_0c00,
        }
    }
}

impl CoocParams {
    /// Fails with [`Error::InvalidParameter`] naming the first out-of-range parameter.
    pub fn validate(&self) -> Result<()> {
        self.keypoints.validate()?;
        if !(2..=256).contains(&self.vocabulary_branching) {
            return Err(Error::param(
                "vocabulary_branching",
                format!("must be in 2..=256, got {}", self.vocabulary_branching),
            ));
        }
        if !(1..=6).contains(&self.vocabulary_depth) {
            return Err(Error::param(
                "vocabulary_depth",
                format!("must be in 1..=6, got {}", self.vocabulary_depth),
            ));
        }
        let leaves = (self.vocabulary_branching as u64).pow(self.vocabulary_depth as u32);
        if leaves > 1 << 24 {
            return Err(Error::inconsistent(
                "vocabulary_depth",
                format!("branching^depth = {leaves} words exceeds 2^24"),
            ));
        }
        if self.kmeans_iterations == 0 {
            return Err(Error::param("kmeans_iterations", "must be at least 1"));
        }
        if self.max_training_descriptors < self.vocabulary_branching {
            return Err(Error::inconsistent(
                "max_training_descriptors",
                format!(
                    "must be at least vocabulary_branching ({}), got {}",
                    self.vocabulary_branching, self.max_training_descriptors
                ),
            ));
        }
        spatial::SpatialGrid::new(self.grid_cols, self.grid_rows)?;
        if self.spatial_tolerance >= self.grid_cols.max(self.grid_rows) {
            return Err(Error::inconsistent(
                "spatial_tolerance",
                format!(
                    "must be below the grid size ({}x{}), got {}",
                    self.grid_cols, self.grid_rows, self.spatial_tolerance
                ),
            ));
        }
        Ok(())
    }

    /// The spatial grid these parameters describe.
    pub fn grid(&self) -> Result<spatial::SpatialGrid> {
        spatial::SpatialGrid::new(self.grid_cols, self.grid_rows)
    }
}

/// A small deterministic PRNG (SplitMix64): k-means seeding and sampling need reproducible
/// randomness, not cryptographic quality, and this avoids a dependency.
#[derive(Clone, Debug)]
pub(crate) struct SplitMix64(u64);

impl SplitMix64 {
    pub(crate) fn new(seed: u64) -> Self {
        SplitMix64(seed)
    }

    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub(crate) fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in `0..n` (`n > 0`).
    pub(crate) fn below(&mut self, n: usize) -> usize {
        ((self.next_u64() as u128 * n as u128) >> 64) as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_params_are_valid() {
        CoocParams::default().validate().unwrap();
    }

    #[test]
    fn validate_names_the_bad_parameter() {
        let p = CoocParams {
            vocabulary_branching: 1,
            ..CoocParams::default()
        };
        let err = p.validate().unwrap_err().to_string();
        assert!(err.contains("vocabulary_branching"), "{err}");
        let p = CoocParams {
            spatial_tolerance: 12,
            ..CoocParams::default()
        };
        let err = p.validate().unwrap_err().to_string();
        assert!(err.contains("spatial_tolerance"), "{err}");
    }

    #[test]
    fn rng_is_deterministic_and_in_range() {
        let mut a = SplitMix64::new(7);
        let mut b = SplitMix64::new(7);
        for _ in 0..100 {
            let (x, y) = (a.below(13), b.below(13));
            assert_eq!(x, y);
            assert!(x < 13);
            let f = a.next_f64();
            b.next_f64();
            assert!((0.0..1.0).contains(&f));
        }
    }
}
