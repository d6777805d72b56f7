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
        let picked = self.trip_prior_images(sample)?;
        let take = picked.len();
        let rows = self.trip_rows(&picked);
        let mut prior = vec![0.0f64; rows.cols()];
        for row in rows.iter_rows() {
            for (p, v) in prior.iter_mut().zip(row) {
                *p += f64::from(*v);
            }
        }
        Ok(prior.iter().map(|p| (p / take as f64) as f32).collect())
    }

    /// The quantised images [`CoocMap::trip_prior`] scores: at most `sample` of the map's own
    /// images, spread evenly over its drives in time order.
    pub fn trip_prior_images(&self, sample: usize) -> Result<Vec<Vec<Word>>> {
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
        Ok((0..take).map(|s| images[s * n / take].clone()).collect())
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
    use super::super::fusion::decisiveness;
    use super::super::keypoints::tests::squares;
    use super::super::{
        best_per_query, localize, CoocMethod, CoocOptions, CoocQueries, SequenceParams,
    };
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
    fn every_method_on_a_fused_map_reads_the_batch_from_one_source() {
        // A day + night map and a batch of day queries with two night ones among them: one
        // query at a time the night queries would be read from the night drive; the batch,
        // mostly day, is read from the day drive alone (`localize::CoocQueries`' single-image
        // method, `fusion::WHOLE_BATCH`).
        let day: Vec<GrayImage> = (0..14).map(|s| scene(s, false)).collect();
        let night: Vec<GrayImage> = (0..14).map(|s| scene(s, true)).collect();
        let day_map =
            CoocMap::build(&params(), &[Drive::sequential(12.0, day.clone()).unwrap()]).unwrap();
        let mut map = day_map.clone();
        map.add_drive(&Drive::sequential(22.0, night.clone()).unwrap())
            .unwrap();
        let mut batch = day.clone();
        batch[4] = night[4].clone();
        batch[9] = night[9].clone();
        let queries = CoocQueries::new(&map, &batch).unwrap();
        let options = options();
        let excl = options.sequence.exclusion;
        let n = Normalization::FlooredColumns;
        let read = |window| best_per_query(&queries.fused_scores(n, excl, window).unwrap());
        let single = queries
            .localize(CoocMethod::Single, &options)
            .unwrap()
            .predictions;
        assert_eq!(single, read(crate::cooc::WHOLE_BATCH));
        assert_ne!(
            single,
            read(1),
            "precondition: per query, the night rows differ"
        );
        let day_only = best_per_query(&map.score_matrices_by_source(queries.words())[0]);
        assert_eq!(single, day_only);

        // The sequence methods too: a batch of 9 day and 5 night frames is read from the day
        // drive alone, as the day map answers it; a window of the sequence length would read
        // the night stretch from the night drive.
        let mut batch = day.clone();
        batch[9..].clone_from_slice(&night[9..]);
        let fused = CoocQueries::new(&map, &batch).unwrap();
        let alone = CoocQueries::new(&day_map, &batch).unwrap();
        assert_ne!(
            fused.similarity(n, excl, options.sequence.length).unwrap(),
            alone.similarity(n, excl, 1).unwrap(),
            "precondition: per window, the night stretch reads the night drive"
        );
        for method in CoocMethod::ALL {
            assert_eq!(
                fused.localize(method, &options).unwrap().predictions,
                alone.localize(method, &options).unwrap().predictions,
                "{method}"
            );
        }
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
