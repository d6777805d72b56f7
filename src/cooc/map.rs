//! [`CoocMap`]: the user-facing co-occurrence map — vocabulary, feature settings and location
//! models of one route — built from one or more mapping [`Drive`]s, extended by further drives,
//! and scored against queries: one location per query ([`CoocMap::recognize_words`]) or the
//! whole score matrix ([`CoocMap::score_matrix`]). The methods built on these are run by
//! [`super::localize()`].
//!
//! The vocabulary is learned from the drives given to [`CoocMap::build`] (the paper trains it on
//! separate urban images; a route's own images are what a deployed map has). Drives added later
//! are quantised with that vocabulary, so a map's words never change meaning.
//!
//! Invariants: every image goes through the same extraction and quantisation; all per-image work
//! runs in parallel (rayon) and the results are deterministic and in input order.

use image::GrayImage;
use rayon::prelude::*;

use super::keypoints::{self, DESCRIPTOR_DIM};
use super::model::{DriveRecord, LocationMap, Word, MAX_LOCATIONS};
use super::recognition::{self, Recognition, Schedule};
use super::vocabulary::{TreeSpec, Vocabulary};
use super::CoocParams;
use crate::{Error, Matrix, Result};

/// One mapping drive of the route: images, the location index of each, and a time key that
/// orders drives for the merging of adjacent drives (Section II-E), e.g. the hour of day.
#[derive(Clone, Debug)]
pub struct Drive {
    time: f64,
    images: Vec<GrayImage>,
    locations: Vec<usize>,
}

impl Drive {
    /// A drive whose image `k` shows location `locations[k]`.
    pub fn new(time: f64, images: Vec<GrayImage>, locations: Vec<usize>) -> Result<Self> {
        Drive::check(time, images.len(), &locations)?;
        Ok(Drive {
            time,
            images,
            locations,
        })
    }

    /// A drive whose image `k` shows location `k` (the usual first mapping drive).
    pub fn sequential(time: f64, images: Vec<GrayImage>) -> Result<Self> {
        let locations = (0..images.len()).collect();
        Drive::new(time, images, locations)
    }

    fn check(time: f64, images: usize, locations: &[usize]) -> Result<()> {
        if !time.is_finite() {
            return Err(Error::param("time", format!("must be finite, got {time}")));
        }
        if images != locations.len() {
            return Err(Error::Shape(format!(
                "a drive has {images} images but {} location indices",
                locations.len()
            )));
        }
        if let Some(&l) = locations.iter().find(|&&l| l >= MAX_LOCATIONS) {
            return Err(Error::param(
                "locations",
                format!("location {l} is beyond the limit of {MAX_LOCATIONS} locations"),
            ));
        }
        Ok(())
    }

    /// Number of images.
    pub fn len(&self) -> usize {
        self.images.len()
    }

    /// True when the drive has no image.
    pub fn is_empty(&self) -> bool {
        self.images.is_empty()
    }
}

/// A feature co-occurrence map of one route.
#[derive(Clone, Debug, PartialEq)]
pub struct CoocMap {
    pub(crate) params: CoocParams,
    pub(crate) vocabulary: Vocabulary,
    pub(crate) locations: LocationMap,
}

impl CoocMap {
    /// Learns the vocabulary from all images of `drives` and builds the location models.
    pub fn build(params: &CoocParams, drives: &[Drive]) -> Result<Self> {
        params.validate()?;
        let features: Vec<DriveFeatures> = drives
            .iter()
            .enumerate()
            .map(|(d, drive)| {
                Ok(DriveFeatures {
                    time: drive.time,
                    features: extract_all(params, d, &drive.images)?,
                    locations: drive.locations.clone(),
                })
            })
            .collect::<Result<_>>()?;
        Self::from_features(params, &features)
    }

    /// [`CoocMap::build`] from features already extracted with `params.keypoints` (e.g. to
    /// build several maps from the same drives without extracting them again).
    pub fn from_features(params: &CoocParams, drives: &[DriveFeatures]) -> Result<Self> {
        let training: Vec<&keypoints::Features> = drives.iter().flat_map(|d| &d.features).collect();
        Self::from_features_and_training(params, &training, drives)
    }

    /// [`CoocMap::from_features`] with the vocabulary learned from `training` instead of from
    /// the drives (the paper trains its vocabulary on a separate set of images). The drives
    /// are then quantised with it; `training` is not part of the map.
    pub fn from_features_and_training(
        params: &CoocParams,
        training: &[&keypoints::Features],
        drives: &[DriveFeatures],
    ) -> Result<Self> {
        params.validate()?;
        for d in drives {
            d.check()?;
        }
        if drives.iter().all(|d| d.features.is_empty()) {
            return Err(Error::Empty(
                "a co-occurrence map needs at least one image".into(),
            ));
        }
        let total: usize = training.iter().map(|f| f.keypoints.len()).sum();
        if total < params.vocabulary_branching {
            return Err(Error::Empty(format!(
                "the training images yield only {total} keypoints, fewer than \
                 vocabulary_branching ({})",
                params.vocabulary_branching
            )));
        }
        // An even stride over all descriptors keeps every part of the route represented.
        let stride = total.div_ceil(params.max_training_descriptors);
        let mut training_set = Vec::with_capacity(total / stride * DESCRIPTOR_DIM + DESCRIPTOR_DIM);
        let all = training
            .iter()
            .flat_map(|f| f.descriptors.chunks_exact(DESCRIPTOR_DIM));
        for d in all.step_by(stride) {
            training_set.extend_from_slice(d);
        }
        let spec = TreeSpec {
            branching: params.vocabulary_branching,
            depth: params.vocabulary_depth,
            iterations: params.kmeans_iterations,
            seed: params.seed,
        };
        let vocabulary = Vocabulary::train(&training_set, DESCRIPTOR_DIM, spec)?;
        let mut map = CoocMap {
            params: params.clone(),
            locations: LocationMap::new(
                params.grid()?,
                params.spatial_tolerance,
                params.merge_adjacent_drives,
            ),
            vocabulary,
        };
        for drive in drives {
            map.add_features(drive)?;
        }
        Ok(map)
    }

    /// Adds a further drive of the same route (its location indices given); the models of the
    /// locations it saw are rebuilt together with the drives adjacent to it in time.
    pub fn add_drive(&mut self, drive: &Drive) -> Result<()> {
        let d = self.locations.drives().len();
        self.add_features(&DriveFeatures {
            time: drive.time,
            features: extract_all(&self.params, d, &drive.images)?,
            locations: drive.locations.clone(),
        })
    }

    /// [`CoocMap::add_drive`] from features extracted with this map's `params().keypoints`.
    pub fn add_features(&mut self, drive: &DriveFeatures) -> Result<()> {
        drive.check()?;
        let images = drive
            .locations
            .iter()
            .zip(&drive.features)
            .collect::<Vec<_>>()
            .par_iter()
            .map(|&(&l, f)| (l as u32, self.quantize_features(f)))
            .collect();
        self.locations.add_drive(DriveRecord {
            time: drive.time,
            images,
        })
    }

    /// The visual words of features extracted with this map's `params().keypoints`.
    pub fn quantize_features(&self, f: &keypoints::Features) -> Vec<Word> {
        f.keypoints
            .iter()
            .enumerate()
            .map(|(k, kp)| Word::new(self.vocabulary.quantize(f.descriptor(k)), kp.x, kp.y))
            .collect()
    }

    /// The quantised features of one image (`name` appears in errors).
    pub fn quantize(&self, name: &str, image: &GrayImage) -> Result<Vec<Word>> {
        let f = keypoints::extract(name, image, &self.params.keypoints)?;
        Ok(self.quantize_features(&f))
    }

    /// Quantises many images in parallel, in order.
    pub fn quantize_all(&self, images: &[GrayImage]) -> Result<Vec<Vec<Word>>> {
        images
            .par_iter()
            .enumerate()
            .map(|(i, img)| self.quantize(&format!("query {i}"), img))
            .collect()
    }

    /// `Q x L` co-occurrence scores (the consistent-group size of every query against every
    /// location, 0 without candidates): the input of the sequence matching and, as a similarity
    /// matrix, of the network-flow graph.
    pub fn score_matrix(&self, queries: &[GrayImage]) -> Result<Matrix> {
        let words = self.quantize_all(queries)?;
        Ok(self.score_matrix_words(&words))
    }

    /// [`CoocMap::score_matrix`] for already quantised queries.
    pub fn score_matrix_words(&self, queries: &[Vec<Word>]) -> Matrix {
        let l = self.locations.locations();
        let rows: Vec<Vec<f32>> = queries
            .par_iter()
            .map(|q| {
                recognition::scores(&self.locations, q)
                    .into_iter()
                    .map(|s| s as f32)
                    .collect()
            })
            .collect();
        let mut m = Matrix::zeros(queries.len(), l);
        for (i, r) in rows.iter().enumerate() {
            m.row_mut(i).copy_from_slice(r);
        }
        m
    }

    /// [`CoocMap::score_matrix_words`] per source ([`LocationMap::sources`]: one per drive
    /// time, then the virtual images'), each `Q x L`; their maximum is the score matrix.
    pub fn score_matrices_by_source(&self, queries: &[Vec<Word>]) -> Vec<Matrix> {
        let (l, sources) = (self.locations.locations(), self.locations.sources().max(1));
        let rows: Vec<Vec<u32>> = queries
            .par_iter()
            .map(|q| recognition::scores_by_source(&self.locations, q))
            .collect();
        (0..sources)
            .map(|d| {
                let mut m = Matrix::zeros(queries.len(), l);
                for (i, r) in rows.iter().enumerate() {
                    for (o, &v) in m.row_mut(i).iter_mut().zip(&r[d * l..(d + 1) * l]) {
                        *o = v as f32;
                    }
                }
                m
            })
            .collect()
    }

    /// The rows an online trip feeds its graph with: [`flow_similarity`] of the score matrix
    /// of the quantised frames (`Q x L`), the same similarity `cooc-flow` solves offline.
    pub fn trip_rows(&self, frames: &[Vec<Word>]) -> Matrix {
        flow_similarity(&self.score_matrix_words(frames))
    }

    /// A trip's prior column means for this map (the counterpart of `trip::column_prior` for
    /// descriptor maps): per location, the mean of [`CoocMap::trip_rows`] over at most
    /// `sample` of the map's own images, spread evenly over its drives in time order.
    pub fn trip_prior(&self, sample: usize) -> Result<Vec<f32>> {
        let images: Vec<&Vec<Word>> = self
            .locations
            .drives()
            .iter()
            .flat_map(|d| d.images.iter().map(|(_, w)| w))
            .collect();
        let n = images.len();
        if n == 0 || self.location_count() == 0 {
            return Err(Error::Empty("the map has no reference images".into()));
        }
        let take = n.min(sample.max(1));
        let picked: Vec<Vec<Word>> = (0..take).map(|s| images[s * n / take].clone()).collect();
        let rows = self.trip_rows(&picked);
        let mut prior = vec![0.0f64; rows.cols()];
        for row in rows.iter_rows() {
            for (p, v) in prior.iter_mut().zip(row) {
                *p += f64::from(*v);
            }
        }
        Ok(prior.iter().map(|p| (p / take as f64) as f32).collect())
    }

    /// The best location of one quantised query.
    pub fn recognize_words(&self, query: &[Word], schedule: Schedule) -> Option<Recognition> {
        recognition::recognize_query(&self.locations, query, schedule)
    }

    /// The settings the map was built with.
    pub fn params(&self) -> &CoocParams {
        &self.params
    }

    /// The visual vocabulary.
    pub fn vocabulary(&self) -> &Vocabulary {
        &self.vocabulary
    }

    /// The location models, drives and inverted index.
    pub fn locations(&self) -> &LocationMap {
        &self.locations
    }

    /// Number of locations on the route.
    pub fn location_count(&self) -> usize {
        self.locations.locations()
    }
}

/// The features of one mapping drive: its time, each image's keypoints and descriptors, and
/// the location each image shows.
#[derive(Clone, Debug, PartialEq)]
pub struct DriveFeatures {
    /// Time key (only the order of drives matters).
    pub time: f64,
    /// Per image, extracted with the map's keypoint settings.
    pub features: Vec<keypoints::Features>,
    /// Location of each image.
    pub locations: Vec<usize>,
}

impl DriveFeatures {
    fn check(&self) -> Result<()> {
        // Same rules as `Drive::new`.
        Drive::check(self.time, self.features.len(), &self.locations)
    }
}

/// Extracts the features of `images` with `params.keypoints`, in parallel (`drive` names the
/// drive in errors).
pub fn extract_all(
    params: &CoocParams,
    drive: usize,
    images: &[GrayImage],
) -> Result<Vec<keypoints::Features>> {
    images
        .par_iter()
        .enumerate()
        .map(|(i, img)| {
            keypoints::extract(&format!("drive {drive} image {i}"), img, &params.keypoints)
        })
        .collect()
}

/// How decisively one source recognises one query: the z-score of the row's peak over the
/// source's own off-peak scores, `(peak - mean) / max(sd, 1)`, where the off-peak scores are
/// those of the source's locations (`present`) more than `exclusion` locations from the peak
/// (its neighbours show the same place). The spread is floored at one correspondence, the
/// resolution of a group size. Without off-peak locations the mean is 0.
///
/// Why a z-score: each source (drive time) has a chance level and a spread of its own at
/// every query (a drive at another time of day gathers chance groups everywhere and no peak),
/// so raw group sizes are not comparable across sources, but the distance of a peak from the
/// source's own noise is.
pub fn decisiveness(row: &[f32], present: &[bool], exclusion: usize) -> f32 {
    let Some((peak_at, peak)) = row
        .iter()
        .zip(present)
        .enumerate()
        .filter(|(_, (_, &p))| p)
        .map(|(j, (&v, _))| (j, v))
        .fold(None, |best: Option<(usize, f32)>, (j, v)| match best {
            Some((_, b)) if b >= v => best,
            _ => Some((j, v)),
        })
    else {
        return 0.0;
    };
    let (mut n, mut sum, mut sq) = (0usize, 0f64, 0f64);
    for (j, (&v, &p)) in row.iter().zip(present).enumerate() {
        if p && j.abs_diff(peak_at) > exclusion {
            n += 1;
            sum += f64::from(v);
            sq += f64::from(v) * f64::from(v);
        }
    }
    let (mean, sd) = if n == 0 {
        (0.0, 1.0)
    } else {
        let mean = sum / n as f64;
        (mean, (sq / n as f64 - mean * mean).max(0.0).sqrt().max(1.0))
    };
    ((f64::from(peak) - mean) / sd) as f32
}

/// Per query, the sources of a fused map from the most to the least decisive: the mean
/// [`decisiveness`] of each source's raw score rows over the `window` queries centred on the
/// query (`window` 1: the query alone; clipped at the ends of the sequence); ties to the lower
/// source index.
///
/// Why: a fused map must keep the evidence of the drives that already recognise a query. Taking
/// the best source per location lets a drive the query does not resemble add its chance peaks
/// to every wrong location; choosing the source whose peaks stand out most from its own noise
/// leaves a query run that one drive recognises decisively with exactly that drive's scores,
/// and lets an added drive speak only where it recognises the run more decisively. A window
/// (the sequence matching's length) makes the choice one per stretch of the route: where no
/// drive is decisive, one query's decisiveness is noise and choosing per query would switch
/// sources from frame to frame (`docs/cooc.md`, measured).
pub fn source_order(
    per_source: &[Matrix],
    present: &[bool],
    exclusion: usize,
    window: usize,
) -> Result<Vec<Vec<usize>>> {
    let (q, l) = check_sources(per_source, present)?;
    let d: Vec<Vec<f64>> = per_source
        .iter()
        .enumerate()
        .map(|(s, m)| {
            (0..q)
                .map(|i| {
                    f64::from(decisiveness(
                        m.row(i),
                        &present[s * l..(s + 1) * l],
                        exclusion,
                    ))
                })
                .collect()
        })
        .collect();
    let w = window.max(1);
    Ok((0..q)
        .map(|i| {
            let lo = i.saturating_sub((w - 1) / 2);
            let hi = lo.saturating_add(w).min(q);
            let mean: Vec<f64> = d
                .iter()
                .map(|ds| ds[lo..hi].iter().sum::<f64>() / (hi - lo) as f64)
                .collect();
            let mut order: Vec<usize> = (0..per_source.len()).collect();
            order.sort_by(|&a, &b| mean[b].total_cmp(&mean[a]).then(a.cmp(&b)));
            order
        })
        .collect())
}

/// Checks that `per_source` are `Q x L` matrices and `present` has `sources x L` flags;
/// returns `(Q, L)`.
fn check_sources(per_source: &[Matrix], present: &[bool]) -> Result<(usize, usize)> {
    let Some(first) = per_source.first() else {
        return Err(Error::Empty("no score matrix to fuse".into()));
    };
    let (q, l) = (first.rows(), first.cols());
    if present.len() != per_source.len() * l
        || per_source.iter().any(|m| m.cols() != l || m.rows() != q)
    {
        return Err(Error::Shape(format!(
            "{} score matrices of {q}x{l} and {} presence flags do not match",
            per_source.len(),
            present.len()
        )));
    }
    Ok((q, l))
}

/// Row `i` of the fused matrix takes every location from the first source in `order[i]` that
/// has it (`present`); a location no source has keeps source 0's value.
fn fuse_rows(per_source: &[Matrix], present: &[bool], order: &[Vec<usize>]) -> Matrix {
    let (q, l) = (per_source[0].rows(), per_source[0].cols());
    let mut out = per_source[0].clone();
    for (i, sources) in order.iter().enumerate().take(q) {
        let dst = out.row_mut(i);
        for (j, o) in dst.iter_mut().enumerate() {
            if let Some(&s) = sources.iter().find(|&&s| present[s * l + j]) {
                *o = per_source[s].get(i, j);
            }
        }
    }
    out
}

/// The raw scores of a fused map as one `Q x L` matrix: each query's row from the source
/// that is most decisive on the rows [`fused_similarity`] gives under `normalization`
/// ([`source_order`] with `exclusion` and `window`). Single-image recognition on a fused map
/// takes its best location from this row (window 1); with one source it is that source's
/// scores.
pub fn fused_scores(
    per_source: &[Matrix],
    present: &[bool],
    normalization: crate::similarity::Normalization,
    exclusion: usize,
    window: usize,
) -> Result<Matrix> {
    let normalised = normalise_sources(per_source, present, normalization)?;
    let order = source_order(&normalised, present, exclusion, window)?;
    Ok(fuse_rows(per_source, present, &order))
}

/// Each source's [`flow_similarity`] normalised on its own over its locations (`present`) and
/// all queries, as a map of that drive alone would normalise it; `Q x L` each, 0 where the
/// source has no training set.
fn normalise_sources(
    per_source: &[Matrix],
    present: &[bool],
    normalization: crate::similarity::Normalization,
) -> Result<Vec<Matrix>> {
    let (q, l) = check_sources(per_source, present)?;
    let mut normalised = Vec::with_capacity(per_source.len());
    for (d, s) in per_source.iter().enumerate() {
        let cols: Vec<usize> = (0..l).filter(|&j| present[d * l + j]).collect();
        let mut full = Matrix::zeros(q, l);
        if !cols.is_empty() {
            let mut c = Matrix::zeros(q, cols.len());
            for i in 0..q {
                let (src, dst) = (s.row(i), c.row_mut(i));
                for (o, &j) in dst.iter_mut().zip(&cols) {
                    *o = src[j] + 1.0;
                }
            }
            let c = normalization.apply(&c)?;
            for i in 0..q {
                let (src, dst) = (c.row(i), full.row_mut(i));
                for (&v, &j) in src.iter().zip(&cols) {
                    dst[j] = v;
                }
            }
        }
        normalised.push(full);
    }
    Ok(normalised)
}

/// The similarity `ĉ` the sequence matching and the flow graph use on a map fused from
/// several drives: each source's scores ([`CoocMap::score_matrices_by_source`]) become
/// [`flow_similarity`] and are normalised over that source's locations (`present`, from
/// [`LocationMap::source_present`]) and over all queries, as a map of that drive alone would
/// normalise them; then each query's row is its most decisive source's ([`source_order`],
/// with `exclusion` and `window`). With one source this is `normalization` applied to [`flow_similarity`] of
/// the scores, as before.
///
/// Why per source and per query: a drive the queries do not resemble (night for day queries)
/// only adds chance groups, at a chance level of its own. Normalising each drive's evidence on
/// its own keeps their scales comparable, and taking each query's row from one source keeps
/// the rows of a query that a drive recognises decisively exactly what that drive alone gives:
/// fusing a drive cannot lower them (`docs/cooc.md`, measured; the best source per location,
/// session 5, still lost up to 0.098 AP on single vocabularies).
pub fn fused_similarity(
    per_source: &[Matrix],
    present: &[bool],
    normalization: crate::similarity::Normalization,
    exclusion: usize,
    window: usize,
) -> Result<Matrix> {
    let normalised = normalise_sources(per_source, present, normalization)?;
    // Decisiveness is measured on the rows the methods read: a location that gathers chance
    // groups with every query (feature-rich) is discounted by the normalisation, so its peaks
    // do not pass for recognition.
    let order = source_order(&normalised, present, exclusion, window)?;
    Ok(fuse_rows(&normalised, present, &order))
}

/// The co-occurrence scores as the similarity matrix `C` of the network-flow graph: `s + 1`.
///
/// Most scores are 0 (no shared word, or no consistent pair), and a graph node with similarity 0
/// is unusable, which would break paths at every frame without features (tunnels). Adding one
/// keeps every node usable at a high cost while preserving the order of scores; apply the usual
/// column normalisation (Eq. 2) afterwards, which then also discounts locations that score
/// highly against every query (e.g. feature-rich scenes).
pub fn flow_similarity(scores: &Matrix) -> Matrix {
    let mut c = scores.clone();
    c.as_mut_slice().iter_mut().for_each(|v| *v += 1.0);
    c
}

#[cfg(test)]
pub(crate) mod tests {
    use super::super::keypoints::tests::squares;
    use super::super::{localize, CoocMethod, CoocOptions, CoocQueries, SequenceParams};
    use super::*;
    use crate::localize::Prediction;
    use crate::similarity::Normalization;

    fn recognize(map: &CoocMap, queries: &[GrayImage]) -> Vec<Prediction> {
        localize(map, queries, CoocMethod::Single, &CoocOptions::default())
            .unwrap()
            .predictions
    }

    fn sequence_match(
        map: &CoocMap,
        queries: &[GrayImage],
        sequence: &SequenceParams,
    ) -> Vec<Prediction> {
        let options = CoocOptions {
            sequence: *sequence,
            ..CoocOptions::default()
        };
        localize(map, queries, CoocMethod::Sequence, &options)
            .unwrap()
            .predictions
    }
    use image::Luma;

    /// A scene: bright squares and dark bars at seeded positions; `night` inverts the contrast
    /// of every other element and drops a third of them (a different appearance of the place).
    pub(crate) fn scene(seed: u64, night: bool) -> GrayImage {
        let mut rng = crate::cooc::SplitMix64::new(seed);
        let corners: Vec<(u32, u32)> = (0..6)
            .map(|_| (rng.below(52) as u32, rng.below(22) as u32))
            .collect();
        let mut img = squares(64, 32, &corners, 7 + (seed % 3) as u32);
        for k in 0..4 {
            let (x, y) = (rng.below(56) as u32, rng.below(26) as u32);
            let (v, w) = if night ^ (k % 2 == 0) {
                (60u8, 3)
            } else {
                (160u8, 2)
            };
            for yy in y..y + 6 {
                for xx in x..x + w {
                    img.put_pixel(xx, yy, Luma([v]));
                }
            }
        }
        if night {
            for p in img.pixels_mut() {
                p.0[0] = 255 - p.0[0];
            }
        }
        img
    }

    pub(crate) fn params() -> CoocParams {
        CoocParams {
            vocabulary_branching: 8,
            vocabulary_depth: 2,
            spatial_tolerance: 1,
            ..CoocParams::default()
        }
    }

    /// Method options for the generated scenes: sequences of 3, no contrast window.
    pub(crate) fn options() -> CoocOptions {
        CoocOptions {
            sequence: SequenceParams {
                length: 3,
                max_step: 2,
                exclusion: 2,
                contrast_window: 0,
                ..SequenceParams::default()
            },
            ..CoocOptions::default()
        }
    }

    #[test]
    fn recognizes_generated_scenes_end_to_end() {
        let refs: Vec<GrayImage> = (0..12).map(|s| scene(s, false)).collect();
        let map =
            CoocMap::build(&params(), &[Drive::sequential(12.0, refs.clone()).unwrap()]).unwrap();
        assert_eq!(map.location_count(), 12);
        let p = recognize(&map, &refs);
        let correct = p.iter().filter(|x| x.reference == x.query).count();
        assert_eq!(correct, 12, "{p:?}");
        let s = map.score_matrix(&refs).unwrap();
        assert_eq!((s.rows(), s.cols()), (12, 12));
        for i in 0..12 {
            let diag = s.get(i, i);
            assert!((0..12).all(|j| s.get(i, j) <= diag), "row {i}");
        }
    }

    #[test]
    fn a_vocabulary_trained_on_separate_images_quantises_the_drives() {
        let day: Vec<GrayImage> = (0..10).map(|s| scene(s, false)).collect();
        let separate: Vec<GrayImage> = (50..70).map(|s| scene(s, false)).collect();
        let p = params();
        let drive = DriveFeatures {
            time: 12.0,
            features: extract_all(&p, 0, &day).unwrap(),
            locations: (0..10).collect(),
        };
        let training = extract_all(&p, 1, &separate).unwrap();
        let refs: Vec<&keypoints::Features> = training.iter().collect();
        let map =
            CoocMap::from_features_and_training(&p, &refs, std::slice::from_ref(&drive)).unwrap();
        let own = CoocMap::from_features(&p, std::slice::from_ref(&drive)).unwrap();
        assert_ne!(
            map.vocabulary(),
            own.vocabulary(),
            "trained on other images"
        );
        assert_eq!(map.location_count(), 10);
        let found = recognize(&map, &day)
            .iter()
            .filter(|x| x.reference == x.query)
            .count();
        assert!(found >= 9, "{found} of 10 found");
        // Too few training keypoints is an error naming the vocabulary size.
        let err = CoocMap::from_features_and_training(&p, &[], &[drive])
            .unwrap_err()
            .to_string();
        assert!(err.contains("vocabulary_branching"), "{err}");
    }

    #[test]
    fn fused_drives_recognize_either_appearance() {
        let day: Vec<GrayImage> = (0..10).map(|s| scene(s, false)).collect();
        let night: Vec<GrayImage> = (0..10).map(|s| scene(s, true)).collect();
        let p = params();
        let day_only =
            CoocMap::build(&p, &[Drive::sequential(12.0, day.clone()).unwrap()]).unwrap();
        let mut fused = CoocMap::build(
            &p,
            &[
                Drive::sequential(12.0, day.clone()).unwrap(),
                Drive::sequential(22.0, night.clone()).unwrap(),
            ],
        )
        .unwrap();
        let hits = |m: &CoocMap, q: &[GrayImage]| {
            recognize(m, q)
                .iter()
                .filter(|x| x.reference == x.query)
                .count()
        };
        assert_eq!(hits(&fused, &day), 10);
        assert_eq!(hits(&fused, &night), 10);
        assert!(
            hits(&day_only, &night) < 10,
            "night should not match a day-only map"
        );
        // A further drive (reversed location order) updates the same models.
        let before = fused.locations().entries();
        let order: Vec<usize> = (0..10).rev().collect();
        let again: Vec<GrayImage> = order
            .iter()
            .map(|&s| scene(s as u64 + 100, false))
            .collect();
        fused
            .add_drive(&Drive::new(18.0, again, order).unwrap())
            .unwrap();
        assert_eq!(fused.location_count(), 10);
        assert!(fused.locations().entries() > before);
        assert_eq!(fused.locations().drives().len(), 3);
    }

    #[test]
    fn sequence_match_follows_the_route_and_survives_encoding() {
        let refs: Vec<GrayImage> = (0..16).map(|s| scene(s, false)).collect();
        let map =
            CoocMap::build(&params(), &[Drive::sequential(0.0, refs.clone()).unwrap()]).unwrap();
        // The query drive stops at location 5 for three frames, then skips ahead two at a time.
        let path = [3usize, 4, 5, 5, 5, 6, 8, 10, 12, 14];
        let queries: Vec<GrayImage> = path.iter().map(|&l| refs[l].clone()).collect();
        let seq = SequenceParams {
            length: 4,
            max_step: 2,
            exclusion: 2,
            contrast_window: 0,
            ..SequenceParams::default()
        };
        let p = sequence_match(&map, &queries, &seq);
        assert_eq!(p.len(), path.len());
        for (pred, &truth) in p.iter().zip(&path) {
            assert_eq!(pred.reference, truth, "query {}", pred.query);
        }
        let back = CoocMap::from_bytes(&map.to_bytes()).unwrap();
        assert_eq!(sequence_match(&back, &queries, &seq), p);
    }

    #[test]
    fn fused_similarity_of_one_source_is_the_normalised_flow_similarity() {
        let mut rng = crate::cooc::SplitMix64::new(3);
        let data = (0..6 * 9).map(|_| rng.below(7) as f32).collect();
        let s = Matrix::from_vec(6, 9, data).unwrap();
        for n in [
            Normalization::None,
            Normalization::Columns,
            Normalization::FlooredColumns,
        ] {
            let fused = fused_similarity(std::slice::from_ref(&s), &[true; 9], n, 2, 3).unwrap();
            assert_eq!(fused, n.apply(&flow_similarity(&s)).unwrap(), "{n:?}");
        }
        let raw = fused_scores(
            std::slice::from_ref(&s),
            &[true; 9],
            Normalization::FlooredColumns,
            2,
            3,
        )
        .unwrap();
        assert_eq!(raw, s);
        let err = fused_similarity(&[s], &[true; 3], Normalization::None, 2, 1).unwrap_err();
        assert!(err.to_string().contains("presence"), "{err}");
        assert!(fused_similarity(&[], &[], Normalization::None, 2, 1).is_err());
    }

    #[test]
    fn decisiveness_is_the_peak_over_the_sources_own_off_peak_noise() {
        let all = [true; 8];
        // A flat row has no peak; a row without any location has none either.
        assert_eq!(decisiveness(&[3.0; 8], &all, 1), 0.0);
        assert_eq!(decisiveness(&[3.0; 8], &[false; 8], 1), 0.0);
        // Peak 10 at 2; its neighbours (1, 3) are not noise; off-peak 0, 2, 0, 2, 0: mean 0.8,
        // sd 0.98 floored at 1 -> 9.2.
        let row = [0.0, 9.0, 10.0, 9.0, 2.0, 0.0, 2.0, 0.0];
        assert!((decisiveness(&row, &all, 1) - 9.2).abs() < 1e-5);
        // The same peak over a noisier source stands out less.
        let noisy = [0.0, 9.0, 10.0, 9.0, 8.0, 0.0, 8.0, 0.0];
        assert!(decisiveness(&noisy, &all, 1) < decisiveness(&row, &all, 1));
        // Shifting or scaling a row's scores by the source's chance level does not change it
        // (spread above the floor).
        let shifted: Vec<f32> = noisy.iter().map(|v| v * 2.0 + 5.0).collect();
        let d = decisiveness(&noisy, &all, 1);
        assert!((decisiveness(&shifted, &all, 1) - d).abs() < 1e-5);
        // Locations the source has no training set of are neither peak nor noise.
        let mut present = all;
        present[2] = false;
        // Peak 9 at 1 (the first of two); off-peak 3..8: 9, 2, 0, 2, 0.
        let d = decisiveness(&row, &present, 1);
        assert!((d - (9.0 - 2.6) / 11.04f32.sqrt()).abs() < 1e-4, "{d}");
        // Ranking: per query, most decisive first, ties to the lower source.
        let a = Matrix::from_vec(2, 8, [row, [1.0; 8]].concat()).unwrap();
        let b = Matrix::from_vec(2, 8, [noisy, [1.0; 8]].concat()).unwrap();
        let order = source_order(&[b.clone(), a.clone()], &[true; 16], 1, 1).unwrap();
        assert_eq!(order, vec![vec![1, 0], vec![0, 1]]);
        // Over a window of 3 queries, query 1 (no peak anywhere) follows its neighbour's choice.
        let order = source_order(&[b, a], &[true; 16], 1, 3).unwrap();
        assert_eq!(order, vec![vec![1, 0], vec![1, 0]]);
    }

    #[test]
    fn a_source_the_queries_do_not_resemble_cannot_outvote_the_one_they_do() {
        // Source 0 (day): query i scores 6 at location i, 0-2 elsewhere. Source 1 (night): no
        // true match, but a chance level of 5-8 everywhere, higher at some locations.
        let (q, l) = (8, 12);
        let mut rng = crate::cooc::SplitMix64::new(11);
        let mut day = Matrix::zeros(q, l);
        let mut night = Matrix::zeros(q, l);
        for i in 0..q {
            for j in 0..l {
                day.set(i, j, rng.below(3) as f32);
                night.set(i, j, 5.0 + rng.below(4) as f32);
            }
            day.set(i, i, 6.0);
        }
        let argmax = |m: &Matrix| -> Vec<usize> {
            (0..q)
                .map(|i| (0..l).fold(0, |b, j| if m.get(i, j) > m.get(i, b) { j } else { b }))
                .collect()
        };
        let truth: Vec<usize> = (0..q).collect();
        let mut raw_max = day.clone();
        for (a, &b) in raw_max.as_mut_slice().iter_mut().zip(night.as_slice()) {
            *a = a.max(b);
        }
        let raw_hits = argmax(&raw_max)
            .iter()
            .zip(&truth)
            .filter(|(a, b)| a == b)
            .count();
        assert!(
            raw_hits < q / 2,
            "the night chance level wins the raw maximum ({raw_hits})"
        );
        let present = vec![true; 2 * l];
        let fused = fused_similarity(
            &[day.clone(), night.clone()],
            &present,
            Normalization::FlooredColumns,
            1,
            3,
        )
        .unwrap();
        assert_eq!(argmax(&fused), truth);
        assert_eq!(
            argmax(
                &fused_scores(
                    &[day.clone(), night.clone()],
                    &present,
                    Normalization::FlooredColumns,
                    1,
                    1
                )
                .unwrap()
            ),
            truth
        );
        // Every row is the day source's alone, normalised as a map of the day drive would.
        let day_alone = Normalization::FlooredColumns
            .apply(&flow_similarity(&day))
            .unwrap();
        assert_eq!(fused, day_alone);
        // A location the most decisive source did not see takes the next source's value.
        let mut present = present;
        present[3] = false;
        let raw = fused_scores(&[day, night.clone()], &present, Normalization::None, 1, 1).unwrap();
        assert_eq!(raw.get(0, 3), night.get(0, 3));
        assert_eq!(raw.get(0, 0), 6.0);
    }

    #[test]
    fn fusing_a_drive_keeps_the_scores_of_queries_the_map_recognises_decisively() {
        // A day map recognises day queries decisively; fusing a night drive of the same places
        // (same vocabulary: `add_drive`) must leave every method's input and answer unchanged.
        let day: Vec<GrayImage> = (0..14).map(|s| scene(s, false)).collect();
        let night: Vec<GrayImage> = (0..14).map(|s| scene(s, true)).collect();
        let p = params();
        let single = CoocMap::build(&p, &[Drive::sequential(12.0, day.clone()).unwrap()]).unwrap();
        let mut fused = single.clone();
        fused
            .add_drive(&Drive::sequential(22.0, night.clone()).unwrap())
            .unwrap();
        assert_eq!(fused.locations().sources(), 2);
        let options = options();
        let excl = options.sequence.exclusion;
        let before = CoocQueries::new(&single, &day).unwrap();
        let after = CoocQueries::new(&fused, &day).unwrap();
        // Precondition: the day source recognises every query decisively, far above its noise.
        let per_source = fused.score_matrices_by_source(after.words());
        assert_eq!(per_source[0], *before.scores());
        for i in 0..day.len() {
            assert!(
                decisiveness(per_source[0].row(i), &[true; 14], excl) > 3.0,
                "query {i}"
            );
        }
        for n in [
            Normalization::FlooredColumns,
            Normalization::Columns,
            Normalization::None,
        ] {
            for w in [1, options.sequence.length] {
                assert_eq!(
                    after.similarity(n, excl, w).unwrap(),
                    before.similarity(n, excl, w).unwrap()
                );
            }
        }
        for n in [Normalization::FlooredColumns, Normalization::None] {
            assert_eq!(after.fused_scores(n, excl, 1).unwrap(), *before.scores());
        }
        for method in CoocMethod::ALL {
            assert_eq!(
                after.localize(method, &options).unwrap().predictions,
                before.localize(method, &options).unwrap().predictions,
                "{method}"
            );
        }
        // The best source per location (session 5's rule) does change these rows: the night
        // drive's normalised chance groups outvote the day drive's at wrong locations.
        let present = fused.locations().source_present();
        let n = Normalization::FlooredColumns;
        let norm: Vec<Matrix> = per_source
            .iter()
            .map(|s| n.apply(&flow_similarity(s)).unwrap())
            .collect();
        let mut per_location_max = norm[0].clone();
        for (a, &b) in per_location_max
            .as_mut_slice()
            .iter_mut()
            .zip(norm[1].as_slice())
        {
            *a = a.max(b);
        }
        assert!(present.iter().all(|&x| x));
        assert_ne!(per_location_max, after.similarity(n, excl, 1).unwrap());
        // And the fused drive still serves the queries it recognises: night queries.
        let night_q = CoocQueries::new(&fused, &night).unwrap();
        let hits = night_q
            .localize(CoocMethod::Single, &options)
            .unwrap()
            .predictions
            .iter()
            .filter(|x| x.reference == x.query)
            .count();
        assert!(hits >= 12, "{hits} of 14 night queries");
    }

    #[test]
    fn flow_similarity_is_positive_and_order_preserving() {
        let s = Matrix::from_vec(1, 3, vec![0.0, 4.0, 2.0]).unwrap();
        assert_eq!(flow_similarity(&s).as_slice(), &[1.0, 5.0, 3.0]);
    }

    #[test]
    fn drive_and_build_errors_are_precise() {
        let err = Drive::new(0.0, vec![GrayImage::new(8, 8)], vec![])
            .unwrap_err()
            .to_string();
        assert!(err.contains("1 images but 0 location"), "{err}");
        assert!(Drive::new(f64::INFINITY, vec![], vec![]).is_err());
        let flat = vec![GrayImage::from_pixel(64, 32, Luma([9])); 3];
        let err = CoocMap::build(&params(), &[Drive::sequential(0.0, flat).unwrap()])
            .unwrap_err()
            .to_string();
        assert!(err.contains("keypoints"), "{err}");
        assert!(CoocMap::build(&params(), &[]).is_err());
    }
}
