//! Location recognition (Sections II-C and II-D): candidate correspondences from the inverted
//! index, the correspondence-consistency matrix `J_i`, iterative elimination down to a globally
//! consistent group `K_i`, and the simultaneous search over all locations bounded by the
//! maximum potential score (the current size of `J_i`).
//!
//! The search runs over *entities*, the training sets of the locations (one per training image
//! or virtual image, see [`super::model`]); a location's score is the best of its entities'.
//! A candidate correspondence pairs a query feature with the row of its visual word in an
//! entity's model. Two candidates are consistent when the model recorded their word pair with
//! the spatial word the query shows between them. Elimination repeatedly removes the candidate
//! consistent with the fewest others (ties: the lowest index, where the paper picks at random, so
//! results are reproducible) until every remaining pair is consistent; the score is the group
//! size.
//!
//! The search over the locations ([`Schedule`]s, [`recognize_query`]) is in
//! `recognition/search.rs`.

mod search;

use rayon::prelude::*;

use super::model::{entry_matches, LocationMap, Word};
pub use search::{recognize_query, recognize_with_runner_up, Recognition, Schedule};

/// The correspondence-consistency matrix of one location and its elimination state.
///
/// Layout for speed: `J` is a bit matrix (one row of `stride` words per candidate), and each
/// candidate's state is one key `score << 32 | candidate` (eliminated: `u64::MAX`), so the
/// weakest candidate (fewest consistent others, ties to the lowest index, as in the paper's
/// rule with a reproducible tie-break) is the minimum key, a branch-free scan, and removing a
/// candidate subtracts its bit row from the keys without looking up who is still alive.
#[derive(Clone, Debug, Default)]
pub struct Elimination {
    stride: usize,
    bits: Vec<u64>,
    keys: Vec<u64>,
    alive: usize,
}

/// Key of an eliminated candidate: above every live key (`score < 2^32`); it stays at or above
/// [`DEAD_FLOOR`] through the later eliminations' subtractions (at most one of `2^32` per
/// candidate, and there are far fewer than `2^31` candidates).
const DEAD: u64 = u64::MAX;
const DEAD_FLOOR: u64 = 1 << 63;

impl Elimination {
    /// Builds `J` for `n` candidates; `consistent(a, b)` is asked once per pair `a < b`.
    pub fn new(n: usize, mut consistent: impl FnMut(usize, usize) -> bool) -> Self {
        let mut e = Elimination::default();
        e.reset(n);
        for a in 0..n {
            for b in a + 1..n {
                if consistent(a, b) {
                    e.connect(a, b);
                }
            }
        }
        e.count();
        e
    }

    /// Empties `J` for `n` candidates, keeping the buffers.
    fn reset(&mut self, n: usize) {
        self.stride = n.div_ceil(64);
        self.bits.clear();
        self.bits.resize(n * self.stride, 0);
        self.keys.clear();
        self.keys.extend(0..n as u64);
        self.alive = n;
    }

    /// Records that candidates `a != b` are consistent (idempotent).
    #[inline]
    fn connect(&mut self, a: usize, b: usize) {
        let stride = self.stride;
        self.bits[a * stride + b / 64] |= 1 << (b % 64);
        self.bits[b * stride + a / 64] |= 1 << (a % 64);
    }

    /// Sets every candidate's score to the number of candidates it is consistent with.
    fn count(&mut self) {
        for (i, k) in self.keys.iter_mut().enumerate() {
            let row = &self.bits[i * self.stride..(i + 1) * self.stride];
            let s: u32 = row.iter().map(|w| w.count_ones()).sum();
            *k = u64::from(s) << 32 | i as u64;
        }
    }

    /// The maximum potential score: the number of candidates still in `J`.
    #[inline]
    pub fn bound(&self) -> usize {
        self.alive
    }

    /// The candidate to eliminate next, or `None` when all remaining ones are consistent.
    #[inline]
    fn weakest(&self) -> Option<usize> {
        let k = self.keys.iter().copied().fold(DEAD, u64::min);
        if k >= DEAD_FLOOR || (k >> 32) as usize + 1 == self.alive {
            None
        } else {
            Some((k & 0xffff_ffff) as usize)
        }
    }

    /// Eliminates one candidate; returns `false` (and does nothing) when already finished.
    pub fn step(&mut self) -> bool {
        let Some(c) = self.weakest() else {
            return false;
        };
        self.keys[c] = DEAD;
        self.alive -= 1;
        let row = &self.bits[c * self.stride..(c + 1) * self.stride];
        for (keys, &w) in self.keys.chunks_mut(64).zip(row) {
            for (j, k) in keys.iter_mut().enumerate() {
                *k -= (w >> j & 1) << 32;
            }
        }
        true
    }

    /// Whether every remaining pair is consistent.
    pub fn finished(&self) -> bool {
        self.weakest().is_none()
    }

    /// Eliminates to the end and returns the score.
    pub fn run(&mut self) -> usize {
        while self.step() {}
        self.bound()
    }

    /// The remaining candidates, sorted.
    pub fn kept(&self) -> Vec<usize> {
        (0..self.keys.len())
            .filter(|&c| self.keys[c] < DEAD_FLOOR)
            .collect()
    }

    /// Each candidate's current number of consistent live candidates (eliminated: none).
    #[cfg(test)]
    fn scores(&self) -> Vec<Option<u32>> {
        self.keys
            .iter()
            .map(|&k| (k < DEAD_FLOOR).then_some((k >> 32) as u32))
            .collect()
    }
}

/// Signed grid offsets between all query features (row-major, `n x n`).
pub(crate) struct QueryGeometry {
    n: usize,
    offsets: Vec<(i16, i16)>,
}

impl QueryGeometry {
    pub(crate) fn new(map: &LocationMap, query: &[Word]) -> Self {
        let n = query.len();
        let g = map.grid();
        let mut offsets = Vec::with_capacity(n * n);
        for a in query {
            for b in query {
                offsets.push(g.offset(g.word(a.pos(), b.pos())));
            }
        }
        QueryGeometry { n, offsets }
    }
}

/// Candidate correspondences grouped by entity: `(entity, [(query feature, row)])`, entities
/// ascending, each entity's candidates by query feature.
pub(crate) struct Candidates {
    groups: Vec<(u32, usize, usize)>,
    items: Vec<(u32, u32)>,
}

impl Candidates {
    /// A counting sort of the postings by entity (two passes over them, no comparison sort):
    /// the query features are visited in order, so each entity's items come out by feature.
    pub(crate) fn gather(map: &LocationMap, query: &[Word]) -> Self {
        let mut start = vec![0u32; map.entities() + 1];
        for f in query {
            for &(entity, _) in map.postings(f.word) {
                start[entity as usize + 1] += 1;
            }
        }
        let mut groups = Vec::new();
        for e in 0..map.entities() {
            let (s, c) = (start[e] as usize, start[e + 1] as usize);
            if c > 0 {
                groups.push((e as u32, s, s + c));
            }
            start[e + 1] = (s + c) as u32;
        }
        let mut items = vec![(0u32, 0u32); start[map.entities()] as usize];
        for (q, f) in query.iter().enumerate() {
            for &(entity, row) in map.postings(f.word) {
                let next = &mut start[entity as usize];
                items[*next as usize] = (q as u32, row);
                *next += 1;
            }
        }
        Candidates { groups, items }
    }

    fn items(&self, group: usize) -> &[(u32, u32)] {
        let (_, s, e) = self.groups[group];
        &self.items[s..e]
    }
}

/// Reusable buffers of [`consistency`].
#[derive(Default)]
struct Scratch {
    /// The candidates as keys `row << 32 | index`, sorted (by row, then index).
    by_row: Vec<u64>,
}

/// Fills `e` with the consistency matrix `J` of `entity` for candidates `(query feature, row)`.
///
/// Built by a merge join rather than one lookup per pair: the candidates are visited in row
/// order, and for candidate `a` the model's run of row `a` (sorted by the other row) is walked
/// once alongside the candidates of higher rows, so a row costs `O(run + n)` instead of `n`
/// binary searches. (A variant that walked each row's run once for all its candidates with a
/// per-row table of candidates gave the same matrix but was ~20 % slower per core: the tight
/// skip loop here streams the run faster.) Same matrix as asking
/// [`super::model::LocationModel::consistent`] for every pair (property-tested).
fn consistency(
    map: &LocationMap,
    geo: &QueryGeometry,
    entity: u32,
    items: &[(u32, u32)],
    scratch: &mut Scratch,
    e: &mut Elimination,
) {
    let model = map.entity_model(entity);
    let tol = map.tolerance() as i16;
    let n = items.len();
    e.reset(n);
    let by_row = &mut scratch.by_row;
    by_row.clear();
    by_row.extend(
        items
            .iter()
            .enumerate()
            .map(|(i, &(_, r))| u64::from(r) << 32 | i as u64),
    );
    by_row.sort_unstable();
    for (pos, &ka) in by_row.iter().enumerate() {
        let a = (ka & 0xffff_ffff) as usize;
        let (qa, ra) = items[a];
        let run = model.run(ra);
        let offsets = &geo.offsets[qa as usize * geo.n..(qa as usize + 1) * geo.n];
        let mut k = 0;
        for &kb in &by_row[pos + 1..] {
            let (b, rb) = ((kb & 0xffff_ffff) as usize, (kb >> 32) as u32);
            while k < run.len() && run[k] >> 16 < rb {
                k += 1;
            }
            if k == run.len() {
                // The run is exhausted: no candidate of a higher row can match.
                break;
            }
            let obs = offsets[items[b].0 as usize];
            if run[k..]
                .iter()
                .take_while(|&&p| p >> 16 == rb)
                .any(|&p| entry_matches(p, obs, tol))
            {
                e.connect(a, b);
            }
        }
    }
    e.count();
}

/// Every location's score for `query` (0 where it has no candidate): full elimination of each
/// entity, the best entity per location.
pub fn scores(map: &LocationMap, query: &[Word]) -> Vec<u32> {
    best_per_slot(map, query, map.locations(), |e| map.entity_location(e))
}

/// Every location's score for `query` from each source separately
/// ([`LocationMap::sources`]): `sources x locations`, source-major, 0 where the source has no
/// candidate at the location. The maximum over the sources is [`scores`].
pub fn scores_by_source(map: &LocationMap, query: &[Word]) -> Vec<u32> {
    let l = map.locations();
    best_per_slot(map, query, map.sources() * l, |e| {
        map.entity_source(e) * l + map.entity_location(e)
    })
}

/// Full elimination of every entity with a candidate; the best score per `slot(entity)`.
///
/// The entities are independent, so they are spread over the rayon pool (one query's row uses
/// both cores; with many concurrent queries the pool simply interleaves them). Each worker
/// reuses one set of buffers for all the entities it scores.
fn best_per_slot(
    map: &LocationMap,
    query: &[Word],
    slots: usize,
    slot: impl Fn(u32) -> usize,
) -> Vec<u32> {
    let geo = QueryGeometry::new(map, query);
    let cands = Candidates::gather(map, query);
    let scored: Vec<u32> = (0..cands.groups.len())
        .into_par_iter()
        .with_min_len(64)
        .map_init(
            || (Scratch::default(), Elimination::default()),
            |(scratch, e), g| {
                consistency(map, &geo, cands.groups[g].0, cands.items(g), scratch, e);
                e.run() as u32
            },
        )
        .collect();
    let mut out = vec![0u32; slots];
    for (&(entity, _, _), s) in cands.groups.iter().zip(scored) {
        let k = slot(entity);
        out[k] = out[k].max(s);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::super::model::DriveRecord;
    use super::super::spatial::SpatialGrid;
    use super::*;
    use crate::cooc::SplitMix64;
    use proptest::prelude::*;

    fn from_matrix(j: &[&[u8]]) -> Elimination {
        Elimination::new(j.len(), |a, b| j[a][b] == 1)
    }

    #[test]
    fn paper_figure_5_keeps_red_green_orange() {
        // 0 blue (consistent with none), 1 purple (with green, red), 2 green, 3 red, 4 orange.
        // green, red and orange are mutually consistent; purple is not with orange.
        let j: [&[u8]; 5] = [
            &[1, 0, 0, 0, 0],
            &[0, 1, 1, 1, 0],
            &[0, 1, 1, 1, 1],
            &[0, 1, 1, 1, 1],
            &[0, 0, 1, 1, 1],
        ];
        let mut e = from_matrix(&j);
        assert_eq!(e.bound(), 5);
        assert_eq!(e.run(), 3);
        assert_eq!(e.kept(), vec![2, 3, 4]);
    }

    #[test]
    fn elimination_keeps_exactly_the_planted_clique() {
        // 12 candidates: a clique {2, 5, 7, 8, 11}; outliers each consistent with 2 clique
        // members and with each other in a sparse ring.
        let clique = [2usize, 5, 7, 8, 11];
        let n = 12;
        let mut j = vec![vec![0u8; n]; n];
        for &a in &clique {
            for &b in &clique {
                j[a][b] = 1;
            }
        }
        let outliers: Vec<usize> = (0..n).filter(|i| !clique.contains(i)).collect();
        for (k, &o) in outliers.iter().enumerate() {
            for &c in &clique[k % 3..k % 3 + 2] {
                j[o][c] = 1;
                j[c][o] = 1;
            }
            let next = outliers[(k + 1) % outliers.len()];
            j[o][next] = 1;
            j[next][o] = 1;
        }
        let rows: Vec<&[u8]> = j.iter().map(|r| r.as_slice()).collect();
        let mut e = from_matrix(&rows);
        assert_eq!(e.run(), clique.len());
        assert_eq!(e.kept(), clique.to_vec());
    }

    #[test]
    fn empty_and_single_candidate_sets() {
        assert_eq!(Elimination::new(0, |_, _| true).run(), 0);
        assert_eq!(Elimination::new(1, |_, _| true).run(), 1);
        assert_eq!(Elimination::new(4, |_, _| false).run(), 1);
        assert_eq!(Elimination::new(70, |_, _| true).run(), 70);
    }

    /// The elimination as first written (an alive list, the weakest found by a scan of it,
    /// scores decremented one live candidate at a time): the reference for [`Elimination`].
    fn reference_elimination(n: usize, edge: impl Fn(usize, usize) -> bool) -> Vec<usize> {
        let mut score: Vec<usize> = (0..n)
            .map(|a| (0..n).filter(|&b| b != a && edge(a, b)).count())
            .collect();
        let mut alive: Vec<usize> = (0..n).collect();
        loop {
            let Some((pos, &c)) = alive
                .iter()
                .enumerate()
                .min_by_key(|&(_, &c)| (score[c], c))
            else {
                return alive;
            };
            if score[c] + 1 == alive.len() {
                alive.sort_unstable();
                return alive;
            }
            alive.swap_remove(pos);
            for &j in &alive {
                if edge(c, j) {
                    score[j] -= 1;
                }
            }
        }
    }

    proptest! {
        #[test]
        fn elimination_matches_the_reference_step_by_step(n in 0usize..150, seed in 0u64..10_000, density in 1usize..8) {
            // Sizes across several 64-bit words; densities from sparse to nearly complete.
            let mut rng = SplitMix64::new(seed);
            let dense: Vec<bool> = (0..n * n).map(|_| rng.below(8) < density).collect();
            let edge = |a: usize, b: usize| a != b && dense[a.min(b) * n + a.max(b)];
            let mut e = Elimination::new(n, edge);
            let expected = reference_elimination(n, edge);
            prop_assert_eq!(e.run(), expected.len());
            prop_assert_eq!(e.kept(), expected);
        }

        #[test]
        fn score_rows_match_pairwise_matrices_and_reference_elimination(seed in 0u64..1000, vocab in 4u32..80, tol in 0u16..3) {
            // The parallel full row (counting-sort gather, merge-join `J`, key-based
            // elimination) against the plainest computation: every candidate pair asked of
            // the model, eliminated by the reference.
            let (_, scenes) = random_map(40, 25, vocab, seed);
            let mut map = LocationMap::new(SpatialGrid::new(12, 8).unwrap(), tol, false);
            let images = scenes.iter().enumerate().map(|(l, s)| (l as u32, s.clone())).collect();
            map.add_drive(DriveRecord { time: 0.0, images }).unwrap();
            let q = noisy_query(&scenes[seed as usize % 40], vocab, seed + 5);
            let geo = QueryGeometry::new(&map, &q);
            let mut expected = vec![0u32; map.locations()];
            for entity in 0..map.entities() as u32 {
                let model = map.entity_model(entity);
                let items: Vec<(usize, u32)> = q
                    .iter()
                    .enumerate()
                    .filter_map(|(i, f)| model.row(f.word).map(|r| (i, r)))
                    .collect();
                let edge = |a: usize, b: usize| {
                    let ((qa, ra), (qb, rb)) = (items[a], items[b]);
                    a != b
                        && if a < b {
                            model.consistent(ra, rb, geo.offsets[qa * geo.n + qb], tol)
                        } else {
                            model.consistent(rb, ra, geo.offsets[qb * geo.n + qa], tol)
                        }
                };
                let s = reference_elimination(items.len(), edge).len() as u32;
                let l = map.entity_location(entity);
                expected[l] = expected[l].max(s);
            }
            prop_assert_eq!(scores(&map, &q), expected);
        }

        #[test]
        fn result_is_always_pairwise_consistent(n in 0usize..40, seed in 0u64..10_000) {
            let mut rng = SplitMix64::new(seed);
            let dense: Vec<bool> = (0..n * n).map(|_| rng.below(3) > 0).collect();
            let edge = |a: usize, b: usize| dense[a.min(b) * n + a.max(b)];
            let mut e = Elimination::new(n, edge);
            let score = e.run();
            let kept = e.kept();
            prop_assert_eq!(kept.len(), score);
            prop_assert!(n == 0 || score >= 1);
            for &a in &kept {
                for &b in &kept {
                    prop_assert!(a == b || edge(a, b));
                }
            }
        }
    }

    /// A map of `locations` random scenes (`features` random words at random positions each),
    /// and queries that copy a scene's features, drop some, and add clutter.
    pub(crate) fn random_map(
        locations: usize,
        features: usize,
        vocabulary: u32,
        seed: u64,
    ) -> (LocationMap, Vec<Vec<Word>>) {
        let mut rng = SplitMix64::new(seed);
        let grid = SpatialGrid::new(12, 8).unwrap();
        let mut map = LocationMap::new(grid, 0, true);
        let mut scenes = Vec::new();
        let mut images = Vec::new();
        for loc in 0..locations {
            let scene: Vec<Word> = (0..features)
                .map(|_| {
                    Word::new(
                        rng.below(vocabulary as usize) as u32,
                        rng.next_f64() as f32,
                        rng.next_f64() as f32,
                    )
                })
                .collect();
            images.push((loc as u32, scene.clone()));
            scenes.push(scene);
        }
        map.add_drive(DriveRecord { time: 0.0, images }).unwrap();
        (map, scenes)
    }

    pub(crate) fn noisy_query(scene: &[Word], vocabulary: u32, seed: u64) -> Vec<Word> {
        let mut rng = SplitMix64::new(seed);
        let mut q: Vec<Word> = scene.iter().filter(|_| rng.below(3) > 0).copied().collect();
        for _ in 0..scene.len() / 2 {
            q.push(Word::new(
                rng.below(vocabulary as usize) as u32,
                rng.next_f64() as f32,
                rng.next_f64() as f32,
            ));
        }
        q
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        #[test]
        fn merge_join_builds_the_same_matrix_as_pairwise_lookups(seed in 0u64..1000, vocab in 4u32..60, tol in 0u16..3) {
            // Small vocabularies: repeated words, equal rows and many pairs per row.
            let (_, scenes) = random_map(8, 20, vocab, seed);
            let mut map = LocationMap::new(SpatialGrid::new(12, 8).unwrap(), tol, false);
            let images = scenes.iter().enumerate().map(|(l, s)| (l as u32, s.clone())).collect();
            map.add_drive(DriveRecord { time: 0.0, images }).unwrap();
            let q = noisy_query(&scenes[seed as usize % 8], vocab, seed + 3);
            let geo = QueryGeometry::new(&map, &q);
            let cands = Candidates::gather(&map, &q);
            for g in 0..cands.groups.len() {
                let entity = cands.groups[g].0;
                let items = cands.items(g);
                let mut fast = Elimination::default();
                consistency(&map, &geo, entity, items, &mut Scratch::default(), &mut fast);
                let model = map.entity_model(entity);
                let slow = Elimination::new(items.len(), |a, b| {
                    let (qa, ra) = items[a];
                    let (qb, rb) = items[b];
                    model.consistent(ra, rb, geo.offsets[qa as usize * geo.n + qb as usize], tol)
                });
                prop_assert_eq!(&fast.bits, &slow.bits);
                prop_assert_eq!(fast.scores(), slow.scores());
            }
        }
    }
}
