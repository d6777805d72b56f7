//! The co-occurrence methods of `seasonloc eval` (`cooc`, `cooc-seq`, `cooc-flow`): their flags,
//! and the map and scores they are computed from.
//!
//! These methods work on the images themselves, not on a global descriptor: each `--reference`
//! folder is one mapping drive of the route (image `k` of every drive = location `k`), from
//! which the vocabulary and the location models are learned ([`build_map`]); the queries are
//! quantised with that vocabulary and localized by the one co-occurrence entry point
//! ([`seasonloc_core::cooc::CoocQueries`]). Every flag left unset keeps the library default
//! ([`CoocParams::default`], [`SequenceParams::default`]), so the CLI never carries a second
//! copy of the defaults.

use std::path::PathBuf;

use clap::Args;
use image::GrayImage;
use rayon::prelude::*;

use seasonloc_core::cooc::{CoocMap, CoocParams, Drive, SequenceParams};
use seasonloc_core::features::{load_image_file_as, Pixels};
use seasonloc_core::Result;

/// Flags of the co-occurrence methods (all optional; unset = the library default).
#[derive(Debug, Clone, Default, Args)]
pub struct CoocArgs {
    /// Co-occurrence: bilinear upsampling before corner detection [default: 2].
    #[arg(long)]
    pub cooc_upsample: Option<u32>,
    /// Co-occurrence: at most this many keypoints per image [default: 300].
    #[arg(long)]
    pub cooc_max_keypoints: Option<usize>,
    /// Co-occurrence: branching factor of the vocabulary tree [default: 32].
    #[arg(long)]
    pub cooc_branching: Option<usize>,
    /// Co-occurrence: depth of the vocabulary tree (words = branching^depth) [default: 2].
    #[arg(long)]
    pub cooc_depth: Option<usize>,
    /// Co-occurrence: spatial grid COLSxROWS [default: 12x8].
    #[arg(long, value_parser = super::parse_size)]
    pub cooc_grid: Option<(u32, u32)>,
    /// Co-occurrence: tolerated grid-offset difference, in cells per axis [default: 1].
    #[arg(long)]
    pub cooc_spatial_tolerance: Option<u16>,
    /// Co-occurrence: seed of the vocabulary's k-means [default: fixed].
    #[arg(long)]
    pub cooc_seed: Option<u64>,
    /// `cooc-seq`: queries per sequence window (ds) [default: 10].
    #[arg(long)]
    pub seq_length: Option<usize>,
    /// `cooc-seq`: largest forward step per query, in locations [default: 3].
    #[arg(long)]
    pub seq_max_step: Option<usize>,
    /// `cooc-seq`: paths ending within this many locations of the best are not runners-up
    /// [default: 10].
    #[arg(long)]
    pub seq_exclusion: Option<usize>,
    /// `cooc-seq`: SeqSLAM's local contrast enhancement of the dissimilarities over this many
    /// locations (0 = off) [default: the library's].
    #[arg(long)]
    pub seq_contrast_window: Option<usize>,
    /// `cooc-seq`: per-location normalisation of the scores before the dissimilarity (floored =
    /// the flow method's floored Eq. 2 on `s + 1`, as `cooc-flow`; eq2 = Eq. 2 exactly; none =
    /// raw scores) [default: floored].
    #[arg(long, value_enum)]
    pub seq_normalization: Option<super::NormalizationArg>,
}

impl CoocArgs {
    /// Validated co-occurrence parameters: the library defaults with the given flags applied.
    pub fn to_params(&self) -> Result<CoocParams> {
        let mut p = CoocParams::default();
        if let Some(u) = self.cooc_upsample {
            p.keypoints.upsample = u;
        }
        if let Some(k) = self.cooc_max_keypoints {
            p.keypoints.max_keypoints = k;
        }
        if let Some(b) = self.cooc_branching {
            p.vocabulary_branching = b;
        }
        if let Some(d) = self.cooc_depth {
            p.vocabulary_depth = d;
        }
        if let Some((c, r)) = self.cooc_grid {
            let cell = |v: u32, name: &str| {
                u16::try_from(v).map_err(|_| {
                    seasonloc_core::Error::param("cooc_grid", format!("{name} {v} is too large"))
                })
            };
            p.grid_cols = cell(c, "columns")?;
            p.grid_rows = cell(r, "rows")?;
        }
        if let Some(t) = self.cooc_spatial_tolerance {
            p.spatial_tolerance = t;
        }
        if let Some(s) = self.cooc_seed {
            p.seed = s;
        }
        p.validate()?;
        Ok(p)
    }

    /// Validated sequence-matching parameters (`cooc-seq`).
    pub fn to_sequence(&self) -> Result<SequenceParams> {
        let d = SequenceParams::default();
        let p = SequenceParams {
            length: self.seq_length.unwrap_or(d.length),
            max_step: self.seq_max_step.unwrap_or(d.max_step),
            exclusion: self.seq_exclusion.unwrap_or(d.exclusion),
            contrast_window: self.seq_contrast_window.unwrap_or(d.contrast_window),
            normalization: self.seq_normalization.map_or(d.normalization, Into::into),
        };
        p.validate()?;
        Ok(p)
    }
}

/// Builds the map from the mapping drives `(image files, time)` and returns it with the query
/// images, all loaded in parallel. Image `k` of every drive is location `k`.
///
/// The map is built exactly as the service builds one (`POST /v1/maps/{id}/images`, then
/// `POST /v1/maps/{id}/drives` per further drive): the vocabulary is learned from the **first**
/// drive given and the others are added with [`CoocMap::add_drive`], so their words keep the
/// first drive's meaning and a fused map from `eval` is the model the service would hold.
/// `time` orders the drives for the interpolation between drives adjacent in time (paper
/// II-E); the order given only decides which drive trains the vocabulary.
pub fn build_map(
    params: &CoocParams,
    drives: &[(&[PathBuf], f64)],
    queries: &[PathBuf],
) -> Result<(CoocMap, Vec<GrayImage>)> {
    let Some(((first, time), rest)) = drives.split_first() else {
        return Err(seasonloc_core::Error::Empty(
            "a co-occurrence map needs at least one mapping drive".into(),
        ));
    };
    let mut map = CoocMap::build(params, &[Drive::sequential(*time, load_gray(first)?)?])?;
    for (files, time) in rest {
        map.add_drive(&Drive::sequential(*time, load_gray(files)?)?)?;
    }
    Ok((map, load_gray(queries)?))
}

fn load_gray(files: &[PathBuf]) -> Result<Vec<GrayImage>> {
    files
        .par_iter()
        .map(|f| Ok(load_image_file_as(f, Pixels::Gray)?.into_luma8()))
        .collect()
}
