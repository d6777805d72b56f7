//! The one entry point of the three co-occurrence localization methods, shared by
//! `seasonloc eval` and the service: [`CoocMethod`] names the method, [`CoocQueries`] holds a
//! quantised query sequence (and its score matrix, computed once and shared by the methods that
//! need it), and [`CoocQueries::localize`] / [`localize`] return the same
//! [`Localization`] as the descriptor methods.
//!
//! * [`CoocMethod::Single`] (`cooc`) — single-image recognition (Sections II-C, II-D): per
//!   query the best location found by the bounded simultaneous search, confidence = the size
//!   of its spatially consistent group; no prediction for a query sharing no visual word with
//!   the map; no hypotheses. On a map fused from several drives: the best location of the
//!   query's most decisive source ([`fused_scores`]: the full score rows of every source are
//!   computed; no prediction when the best score is 0).
//! * [`CoocMethod::Sequence`] (`cooc-seq`) — the paper's forward-only, variable-speed sequence
//!   matching (II-F) on the score matrix; one prediction per query; no hypotheses.
//! * [`CoocMethod::Flow`] (`cooc-flow`) — the score matrix as the similarity matrix of the
//!   flow paper's graph ([`super::flow_similarity`], then the options' normalisation; on a map
//!   fused from several drives each drive's scores are normalised on their own and each query
//!   takes its most decisive drive's row, [`fused_similarity`], as for `cooc-seq`), solved with the
//!   same solver and confidence as HOG/CNN maps.
//!
//! Why one place: the CLI and the service used to choose between the methods separately, with
//! two enums for one concept; now both call this module, so the same map, queries and options
//! give the same predictions everywhere.

use std::str::FromStr;
use std::sync::OnceLock;
use std::time::Instant;

use image::GrayImage;
use rayon::prelude::*;

use super::fusion::{fused_scores, fused_similarity, WHOLE_BATCH};
use super::map::CoocMap;
use super::model::Word;
use super::recognition::Schedule;
use super::sequence::{match_sequences, SequenceParams};
use crate::localize::Prediction;
use crate::localize::{solve_with_confidence, Localization, LocalizeOptions, StageTimings};
use crate::similarity::Normalization;
use crate::solver::Solution;
use crate::{Error, Matrix, Result};

/// The co-occurrence localization methods.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum CoocMethod {
    /// Single-image recognition (`cooc`).
    #[cfg_attr(feature = "serde", serde(rename = "cooc"))]
    Single,
    /// The paper's sequence matching (`cooc-seq`).
    #[cfg_attr(feature = "serde", serde(rename = "cooc-seq"))]
    Sequence,
    /// The co-occurrence scores in the flow graph (`cooc-flow`; the service's default).
    #[default]
    #[cfg_attr(feature = "serde", serde(rename = "flow"))]
    Flow,
}

impl CoocMethod {
    /// Every method, in the order of their names above.
    pub const ALL: [CoocMethod; 3] = [CoocMethod::Single, CoocMethod::Sequence, CoocMethod::Flow];

    /// The method's name in `seasonloc eval --method` (`cooc`, `cooc-seq`, `cooc-flow`).
    pub fn name(self) -> &'static str {
        match self {
            CoocMethod::Single => "cooc",
            CoocMethod::Sequence => "cooc-seq",
            CoocMethod::Flow => "cooc-flow",
        }
    }

    /// Whether the method works on the `Q x L` score matrix (sequence and flow do; single-image
    /// recognition prunes locations instead of scoring them all).
    pub fn needs_scores(self) -> bool {
        !matches!(self, CoocMethod::Single)
    }
}

impl std::fmt::Display for CoocMethod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for CoocMethod {
    type Err = Error;

    /// Parses a name given by [`CoocMethod::name`].
    fn from_str(s: &str) -> Result<Self> {
        CoocMethod::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                Error::param(
                    "method",
                    format!("unknown co-occurrence method `{s}`; use cooc, cooc-seq or cooc-flow"),
                )
            })
    }
}

/// Settings of the methods that need them (each method reads only its own).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CoocOptions {
    /// Sequence matching (`cooc-seq`).
    pub sequence: SequenceParams,
    /// Graph, solver, normalisation and confidence (`cooc-flow`).
    pub flow: LocalizeOptions,
    /// On a map fused from several drives, `cooc-seq` and `cooc-flow` take each query's row
    /// from the source most decisive over this many queries centred on it
    /// ([`super::source_order`]); 0 (the default) = the whole batch ([`WHOLE_BATCH`]: one
    /// source for the batch, as single-image recognition chooses it; `docs/cooc.md`, session
    /// 13).
    pub fusion_window: usize,
}

impl CoocOptions {
    /// The window of [`CoocOptions::fusion_window`], resolved.
    fn window(&self) -> usize {
        if self.fusion_window == 0 {
            WHOLE_BATCH
        } else {
            self.fusion_window
        }
    }
}

/// A quantised query sequence on one map, with its score matrix computed on first use.
pub struct CoocQueries<'m> {
    map: &'m CoocMap,
    words: Vec<Vec<Word>>,
    scores: OnceLock<Scored>,
}

/// The score matrix (maximum over sources), the per-source matrices when the map has more
/// than one source, and the seconds they took.
struct Scored {
    max: Matrix,
    per_source: Vec<Matrix>,
    seconds: f64,
}

impl<'m> CoocQueries<'m> {
    /// Extracts and quantises the query images (in parallel, in order).
    pub fn new(map: &'m CoocMap, images: &[GrayImage]) -> Result<Self> {
        Ok(Self::from_words(map, map.quantize_all(images)?))
    }

    /// Queries already quantised with `map`'s vocabulary.
    pub fn from_words(map: &'m CoocMap, words: Vec<Vec<Word>>) -> Self {
        CoocQueries {
            map,
            words,
            scores: OnceLock::new(),
        }
    }

    /// The map the queries were quantised with.
    pub fn map(&self) -> &'m CoocMap {
        self.map
    }

    /// Number of queries.
    pub fn len(&self) -> usize {
        self.words.len()
    }

    /// True without queries.
    pub fn is_empty(&self) -> bool {
        self.words.is_empty()
    }

    /// The quantised features of every query, in order.
    pub fn words(&self) -> &[Vec<Word>] {
        &self.words
    }

    /// The `Q x L` score matrix (consistent-group sizes), computed once.
    pub fn scores(&self) -> &Matrix {
        &self.scored().max
    }

    /// Seconds the score matrix took (0 before it is computed).
    pub fn score_seconds(&self) -> f64 {
        self.scores.get().map_or(0.0, |s| s.seconds)
    }

    fn scored(&self) -> &Scored {
        self.scores.get_or_init(|| {
            let t = Instant::now();
            let (max, per_source) = if self.map.locations().sources() > 1 {
                let per_source = self.map.score_matrices_by_source(&self.words);
                let mut max = per_source[0].clone();
                for m in &per_source[1..] {
                    for (a, &b) in max.as_mut_slice().iter_mut().zip(m.as_slice()) {
                        *a = a.max(b);
                    }
                }
                (max, per_source)
            } else {
                (self.map.score_matrix_words(&self.words), Vec::new())
            };
            Scored {
                max,
                per_source,
                seconds: t.elapsed().as_secs_f64(),
            }
        })
    }

    /// The similarity `ĉ` of the sequence matching and the flow graph under `normalization`:
    /// [`fused_similarity`] of the per-source scores, each query's sources ranked with
    /// `exclusion` over `window` queries (with one source: `normalization` of `scores + 1`).
    pub fn similarity(
        &self,
        normalization: Normalization,
        exclusion: usize,
        window: usize,
    ) -> Result<Matrix> {
        let scored = self.scored();
        let (sources, present) = if scored.per_source.is_empty() {
            (
                std::slice::from_ref(&scored.max),
                vec![true; scored.max.cols()],
            )
        } else {
            (
                &scored.per_source[..],
                self.map.locations().source_present(),
            )
        };
        fused_similarity(sources, &present, normalization, exclusion, window)
    }

    /// The raw scores with each query's row from its most decisive source ([`fused_scores`],
    /// ranked on the rows under `normalization` with `exclusion` over `window` queries); with one
    /// source, [`CoocQueries::scores`].
    pub fn fused_scores(
        &self,
        normalization: Normalization,
        exclusion: usize,
        window: usize,
    ) -> Result<Matrix> {
        let scored = self.scored();
        if scored.per_source.is_empty() {
            Ok(scored.max.clone())
        } else {
            let present = self.map.locations().source_present();
            fused_scores(
                &scored.per_source,
                &present,
                normalization,
                exclusion,
                window,
            )
        }
    }

    /// Localizes the sequence with `method`. `timings.similarity` is the score matrix (when this
    /// call computed it) and, for `cooc-flow`, the normalisation; `timings.solve` the method.
    pub fn localize(&self, method: CoocMethod, options: &CoocOptions) -> Result<Localization> {
        let empty = Solution {
            hidden_cost: 0.0,
            hypotheses: Vec::new(),
        };
        if self.words.is_empty() {
            return Err(Error::Empty("no query images to localize".into()));
        }
        let started = Instant::now();
        match method {
            CoocMethod::Single => {
                let predictions = self.single(options.sequence.exclusion)?;
                Ok(Localization {
                    solution: empty,
                    predictions,
                    timings: StageTimings {
                        similarity: 0.0,
                        solve: started.elapsed().as_secs_f64(),
                    },
                })
            }
            CoocMethod::Sequence => {
                let params = options.sequence;
                params.validate()?;
                // Several sources: normalise each on its own, each query's row from its most
                // decisive source (fused_similarity); the sequence matching then works on that
                // similarity as it is. Unnormalised: the most decisive source's raw scores.
                let sources = self.map.locations().sources() > 1;
                let fused = sources && params.normalization != Normalization::None;
                let input = if fused {
                    self.similarity(params.normalization, params.exclusion, options.window())?
                } else if sources {
                    self.fused_scores(Normalization::None, params.exclusion, options.window())?
                } else {
                    self.scores().clone()
                };
                let params = SequenceParams {
                    normalization: if fused {
                        Normalization::None
                    } else {
                        params.normalization
                    },
                    ..params
                };
                let similarity = started.elapsed().as_secs_f64();
                let t = Instant::now();
                let predictions = match_sequences(&input, &params)?;
                Ok(Localization {
                    solution: empty,
                    predictions,
                    timings: StageTimings {
                        similarity,
                        solve: t.elapsed().as_secs_f64(),
                    },
                })
            }
            CoocMethod::Flow => {
                options.flow.solver.validate()?;
                let chat = self.similarity(
                    options.flow.normalization,
                    options.sequence.exclusion,
                    options.window(),
                )?;
                let similarity = started.elapsed().as_secs_f64();
                let t = Instant::now();
                let (solution, mut predictions) = solve_with_confidence(&chat, &options.flow)?;
                // The calibration was fitted on descriptor similarities, not on co-occurrence
                // scores: these predictions have no calibrated probability.
                for p in &mut predictions {
                    p.p_correct = None;
                }
                Ok(Localization {
                    solution,
                    predictions,
                    timings: StageTimings {
                        similarity,
                        solve: t.elapsed().as_secs_f64(),
                    },
                })
            }
        }
    }

    /// Best-first single-image recognition of every query, in parallel; on a fused map, each
    /// query's best location in the source the batch resembles most decisively (mean
    /// decisiveness over the whole batch, [`WHOLE_BATCH`], on the rows floored-normalised per
    /// source, with `exclusion`; ties to the lowest location, as the search breaks them).
    ///
    /// Why the batch and not the query alone: a batch is one camera at one time of day, the
    /// time the paper reads its query's model by (section II-E); one query's decisiveness is
    /// too noisy to choose between two drives of similar conditions, and choosing per query
    /// lost AP where a drive was added to a map the queries were already recognised on
    /// (`docs/cooc.md`, session 13). A batch that mixes times of day is read with the drive
    /// most of it resembles.
    fn single(&self, exclusion: usize) -> Result<Vec<Prediction>> {
        if self.map.locations().sources() > 1 {
            let scores = self.fused_scores(Normalization::default(), exclusion, WHOLE_BATCH)?;
            return Ok(best_per_query(&scores));
        }
        Ok(self
            .words
            .par_iter()
            .enumerate()
            .filter_map(|(i, q)| {
                self.map
                    .recognize_words(q, Schedule::BestFirst)
                    .map(|r| Prediction {
                        query: i,
                        reference: r.location,
                        confidence: r.score as f64,
                        p_correct: None,
                    })
            })
            .collect())
    }
}

/// The single-image readout of a `Q x L` score matrix: each query's best location (ties to the
/// lowest, as the best-first search breaks them) with its score as the confidence; a query
/// whose best score is not positive has no prediction.
pub fn best_per_query(scores: &Matrix) -> Vec<Prediction> {
    scores
        .iter_rows()
        .enumerate()
        .filter_map(|(i, row)| {
            let (best, &s) = row
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.total_cmp(b.1).then(b.0.cmp(&a.0)))?;
            (s > 0.0).then_some(Prediction {
                query: i,
                reference: best,
                confidence: f64::from(s),
                p_correct: None,
            })
        })
        .collect()
}

/// Localizes the query images (in driving order) on `map` with `method`: the one call for a
/// single method. To score several methods on the same queries, build [`CoocQueries`] once.
pub fn localize(
    map: &CoocMap,
    queries: &[GrayImage],
    method: CoocMethod,
    options: &CoocOptions,
) -> Result<Localization> {
    CoocQueries::new(map, queries)?.localize(method, options)
}

#[cfg(test)]
mod tests {
    use super::super::map::tests::{options, params, scene};
    use super::super::Drive;
    use super::*;

    #[test]
    fn names_round_trip_and_unknown_names_are_refused() {
        for m in CoocMethod::ALL {
            assert_eq!(m.name().parse::<CoocMethod>().unwrap(), m);
        }
        let err = "flow".parse::<CoocMethod>().unwrap_err().to_string();
        assert!(err.contains("cooc-flow"), "{err}");
    }

    #[test]
    fn every_method_localizes_generated_scenes_and_shares_one_score_matrix() {
        let refs: Vec<GrayImage> = (0..14).map(|s| scene(s, false)).collect();
        let map =
            CoocMap::build(&params(), &[Drive::sequential(0.0, refs.clone()).unwrap()]).unwrap();
        let queries = CoocQueries::new(&map, &refs).unwrap();
        let options = options();
        for method in CoocMethod::ALL {
            let out = queries.localize(method, &options).unwrap();
            let correct = out
                .predictions
                .iter()
                .filter(|p| p.reference == p.query)
                .count();
            assert!(correct >= 12, "{method}: {correct} of 14 correct");
            assert_eq!(
                out.solution.hypotheses.is_empty(),
                method != CoocMethod::Flow
            );
            // The single-function entry point gives the same answer.
            let again = localize(&map, &refs, method, &options).unwrap();
            assert_eq!(again.predictions, out.predictions, "{method}");
        }
        assert_eq!(queries.scores().rows(), 14);
    }

    #[test]
    fn bad_options_and_empty_queries_are_errors() {
        let refs: Vec<GrayImage> = (0..4).map(|s| scene(s, false)).collect();
        let map =
            CoocMap::build(&params(), &[Drive::sequential(0.0, refs.clone()).unwrap()]).unwrap();
        let bad = CoocOptions {
            sequence: SequenceParams {
                length: 0,
                ..SequenceParams::default()
            },
            ..CoocOptions::default()
        };
        let err = localize(&map, &refs, CoocMethod::Sequence, &bad)
            .unwrap_err()
            .to_string();
        assert!(err.contains("length"), "{err}");
        assert!(localize(&map, &[], CoocMethod::Single, &CoocOptions::default()).is_err());
    }
}
