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
//! Search [`Schedule`]s, all returning the same best location (highest score, ties to the lowest
//! location index):
//! * `Exhaustive` — every location with a candidate is eliminated to the end, one after another
//!   (the baseline of the paper's speed comparison);
//! * `Lockstep` — the paper's simultaneous matching: every round removes one candidate from each
//!   live location, a finished location sets the best score, and a location whose bound falls
//!   below it is dropped;
//! * `BestFirst` — the same bound used as a priority: the location with the highest bound is
//!   advanced next (its `J` is built only then), so the first location to finish is the answer
//!   and locations whose initial bound is below the winner's score are never built.
//!
//! Invariant: a location is only ever dropped when its bound (which never increases and is never
//! below its final score) proves it cannot beat or tie-win against the current best.

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap};

use super::model::{entry_matches, LocationMap, Word};

/// How [`recognize_query`] searches the locations.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Schedule {
    /// Every location separately and completely.
    Exhaustive,
    /// The paper's simultaneous matching, one elimination per location per round.
    Lockstep,
    /// Simultaneous matching advancing the highest bound first (default).
    #[default]
    BestFirst,
}

/// The best location for one query.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Recognition {
    /// Best location.
    pub location: usize,
    /// Its score: the size of its spatially consistent group.
    pub score: usize,
    /// Entities (training sets) whose consistency matrix was built (the work done).
    pub evaluated: usize,
}

/// The correspondence-consistency matrix of one location and its elimination state.
#[derive(Clone, Debug)]
pub struct Elimination {
    stride: usize,
    bits: Vec<u64>,
    alive: Vec<u32>,
    score: Vec<u32>,
}

impl Elimination {
    /// Builds `J` for `n` candidates; `consistent(a, b)` is asked once per pair `a < b`.
    pub fn new(n: usize, mut consistent: impl FnMut(usize, usize) -> bool) -> Self {
        let mut e = Elimination::empty(n);
        for a in 0..n {
            for b in a + 1..n {
                if consistent(a, b) {
                    e.connect(a, b);
                }
            }
        }
        e
    }

    /// `J` of `n` candidates without any consistent pair yet.
    fn empty(n: usize) -> Self {
        let stride = n.div_ceil(64);
        Elimination {
            stride,
            bits: vec![0u64; n * stride],
            alive: (0..n as u32).collect(),
            score: vec![0u32; n],
        }
    }

    /// Records that candidates `a != b` are consistent (each pair at most once).
    #[inline]
    fn connect(&mut self, a: usize, b: usize) {
        let stride = self.stride;
        self.bits[a * stride + b / 64] |= 1 << (b % 64);
        self.bits[b * stride + a / 64] |= 1 << (a % 64);
        self.score[a] += 1;
        self.score[b] += 1;
    }

    /// The maximum potential score: the number of candidates still in `J`.
    #[inline]
    pub fn bound(&self) -> usize {
        self.alive.len()
    }

    /// The candidate to eliminate next, or `None` when all remaining ones are consistent.
    fn weakest(&self) -> Option<usize> {
        let (pos, &c) = self
            .alive
            .iter()
            .enumerate()
            .min_by_key(|&(_, &c)| (self.score[c as usize], c))?;
        if self.score[c as usize] as usize + 1 == self.alive.len() {
            None
        } else {
            Some(pos)
        }
    }

    /// Eliminates one candidate; returns `false` (and does nothing) when already finished.
    pub fn step(&mut self) -> bool {
        let Some(pos) = self.weakest() else {
            return false;
        };
        let c = self.alive.swap_remove(pos) as usize;
        let row = &self.bits[c * self.stride..(c + 1) * self.stride];
        for &j in &self.alive {
            if row[j as usize / 64] >> (j % 64) & 1 == 1 {
                self.score[j as usize] -= 1;
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
        let mut k: Vec<usize> = self.alive.iter().map(|&c| c as usize).collect();
        k.sort_unstable();
        k
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

/// Candidate correspondences grouped by entity: `(entity, [(query feature, row)])`.
pub(crate) struct Candidates {
    groups: Vec<(u32, usize, usize)>,
    items: Vec<(u32, u32)>,
}

impl Candidates {
    pub(crate) fn gather(map: &LocationMap, query: &[Word]) -> Self {
        let mut triples: Vec<(u32, u32, u32)> = Vec::new();
        for (q, f) in query.iter().enumerate() {
            for &(entity, row) in map.postings(f.word) {
                triples.push((entity, q as u32, row));
            }
        }
        triples.sort_unstable();
        let mut groups = Vec::new();
        let mut start = 0;
        for i in 1..=triples.len() {
            if i == triples.len() || triples[i].0 != triples[start].0 {
                groups.push((triples[start].0, start, i));
                start = i;
            }
        }
        let items = triples.iter().map(|&(_, q, r)| (q, r)).collect();
        Candidates { groups, items }
    }

    fn elimination(&self, map: &LocationMap, geo: &QueryGeometry, group: usize) -> Elimination {
        let (entity, s, e) = self.groups[group];
        consistency(map, geo, entity, &self.items[s..e])
    }
}

/// The consistency matrix `J` of `entity` for candidates `(query feature, row)`.
///
/// Built by a merge join rather than one lookup per pair: the candidates are visited in row
/// order, and for candidate `a` the model's run of row `a` (sorted by the other row) is walked
/// once alongside the candidates of higher rows, so a row costs `O(run + n)` instead of `n`
/// binary searches. Same matrix as asking [`super::model::LocationModel::consistent`] for
/// every pair (property-tested).
fn consistency(
    map: &LocationMap,
    geo: &QueryGeometry,
    entity: u32,
    items: &[(u32, u32)],
) -> Elimination {
    let model = map.entity_model(entity);
    let tol = map.tolerance() as i16;
    let n = items.len();
    let mut by_row: Vec<u32> = (0..n as u32).collect();
    by_row.sort_unstable_by_key(|&i| (items[i as usize].1, i));
    let mut e = Elimination::empty(n);
    for (pos, &a) in by_row.iter().enumerate() {
        let (qa, ra) = items[a as usize];
        let run = model.run(ra);
        let offsets = &geo.offsets[qa as usize * geo.n..(qa as usize + 1) * geo.n];
        let mut k = 0;
        for &b in &by_row[pos + 1..] {
            let (qb, rb) = items[b as usize];
            while k < run.len() && run[k] >> 16 < rb {
                k += 1;
            }
            if k == run.len() {
                // The run is exhausted: no candidate of a higher row can match.
                break;
            }
            let obs = offsets[qb as usize];
            if run[k..]
                .iter()
                .take_while(|&&p| p >> 16 == rb)
                .any(|&p| entry_matches(p, obs, tol))
            {
                e.connect(a as usize, b as usize);
            }
        }
    }
    e
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
fn best_per_slot(
    map: &LocationMap,
    query: &[Word],
    slots: usize,
    slot: impl Fn(u32) -> usize,
) -> Vec<u32> {
    let geo = QueryGeometry::new(map, query);
    let cands = Candidates::gather(map, query);
    let mut out = vec![0u32; slots];
    for g in 0..cands.groups.len() {
        let k = slot(cands.groups[g].0);
        let s = cands.elimination(map, &geo, g).run() as u32;
        out[k] = out[k].max(s);
    }
    out
}

/// Best-first search: candidate *counts* come from the inverted index (no grouping of the
/// correspondences), and an entity's candidates and `J` are only materialised when its bound
/// is the highest of all. Returns `((score, entity), runner-up, evaluated)`.
///
/// With `exclusion = Some(x)` the search goes on after the answer until the best entity whose
/// location is more than `x` locations from the answer's finishes: the runner-up score (0 when
/// there is none). Entities near the answer are dropped unbuilt; the bound still prunes the
/// rest, since the first entity to finish outside the window has the highest score there.
fn best_first(
    map: &LocationMap,
    query: &[Word],
    geo: &QueryGeometry,
    exclusion: Option<usize>,
) -> (Option<(usize, u32)>, usize, usize) {
    let mut counts = vec![0u32; map.entities()];
    let mut touched = Vec::new();
    for f in query {
        for &(entity, _) in map.postings(f.word) {
            let c = &mut counts[entity as usize];
            if *c == 0 {
                touched.push(entity);
            }
            *c += 1;
        }
    }
    let mut heap: BinaryHeap<(usize, Reverse<u32>)> = touched
        .iter()
        .map(|&e| (counts[e as usize] as usize, Reverse(e)))
        .collect();
    let mut states: HashMap<u32, Elimination> = HashMap::new();
    let mut evaluated = 0;
    let mut winner: Option<(usize, u32)> = None;
    while let Some((_, Reverse(entity))) = heap.pop() {
        if let (Some((_, w)), Some(x)) = (winner, exclusion) {
            if map.entity_location(w).abs_diff(map.entity_location(entity)) <= x {
                continue;
            }
        }
        let e = states.entry(entity).or_insert_with(|| {
            evaluated += 1;
            let model = map.entity_model(entity);
            let items: Vec<(u32, u32)> = query
                .iter()
                .enumerate()
                .filter_map(|(q, f)| model.row(f.word).map(|r| (q as u32, r)))
                .collect();
            consistency(map, geo, entity, &items)
        });
        // Keep eliminating while this entity stays at the top (same as push + pop).
        loop {
            if !e.step() {
                // Highest bound of all, ties to the lowest entity: this is the answer (or,
                // after it, the runner-up outside the exclusion window).
                if winner.is_some() {
                    return (winner, e.bound(), evaluated);
                }
                winner = Some((e.bound(), entity));
                if exclusion.is_none() {
                    return (winner, 0, evaluated);
                }
                break;
            }
            let key = (e.bound(), Reverse(entity));
            if heap.peek().is_some_and(|&top| top > key) {
                heap.push(key);
                break;
            }
        }
    }
    (winner, 0, evaluated)
}

/// The best location for `query` (best-first) and the score of the best location more than
/// `exclusion` locations away from it (0 when none shares a word with the query): the
/// distinctiveness of the answer. `None` when no location shares a visual word with `query`.
pub fn recognize_with_runner_up(
    map: &LocationMap,
    query: &[Word],
    exclusion: usize,
) -> Option<(Recognition, usize)> {
    let geo = QueryGeometry::new(map, query);
    let (best, runner_up, evaluated) = best_first(map, query, &geo, Some(exclusion));
    best.map(|(score, entity)| {
        (
            Recognition {
                location: map.entity_location(entity),
                score,
                evaluated,
            },
            runner_up,
        )
    })
}

/// `better(score, entity, best)`: higher score wins, ties go to the lower entity (entities are
/// numbered in location order, so this is the lower location).
fn better(score: usize, l: u32, best: &Option<(usize, u32)>) -> bool {
    match best {
        None => true,
        Some((bs, bl)) => score > *bs || (score == *bs && l < *bl),
    }
}

/// The best location for `query`, or `None` when no location shares a visual word with it.
pub fn recognize_query(
    map: &LocationMap,
    query: &[Word],
    schedule: Schedule,
) -> Option<Recognition> {
    let geo = QueryGeometry::new(map, query);
    let (best, evaluated) = match schedule {
        Schedule::BestFirst => {
            let (best, _, evaluated) = best_first(map, query, &geo, None);
            (best, evaluated)
        }
        Schedule::Exhaustive => {
            let cands = Candidates::gather(map, query);
            let mut best = None;
            for g in 0..cands.groups.len() {
                let s = cands.elimination(map, &geo, g).run();
                let l = cands.groups[g].0;
                if better(s, l, &best) {
                    best = Some((s, l));
                }
            }
            (best, cands.groups.len())
        }
        Schedule::Lockstep => {
            let cands = Candidates::gather(map, query);
            let mut live: Vec<(u32, Elimination)> = (0..cands.groups.len())
                .map(|g| (cands.groups[g].0, cands.elimination(map, &geo, g)))
                .collect();
            let evaluated = live.len();
            let mut best: Option<(usize, u32)> = None;
            while !live.is_empty() {
                live.retain_mut(|(l, e)| {
                    if !better(e.bound(), *l, &best) {
                        return false; // cannot beat the best any more
                    }
                    if e.step() {
                        return true;
                    }
                    best = Some((e.bound(), *l));
                    false
                });
            }
            (best, evaluated)
        }
    };
    best.map(|(score, entity)| Recognition {
        location: map.entity_location(entity),
        score,
        evaluated,
    })
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

    proptest! {
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
                let (entity, s0, e0) = cands.groups[g];
                let items = &cands.items[s0..e0];
                let fast = consistency(&map, &geo, entity, items);
                let model = map.entity_model(entity);
                let slow = Elimination::new(items.len(), |a, b| {
                    let (qa, ra) = items[a];
                    let (qb, rb) = items[b];
                    model.consistent(ra, rb, geo.offsets[qa as usize * geo.n + qb as usize], tol)
                });
                prop_assert_eq!(&fast.bits, &slow.bits);
                prop_assert_eq!(&fast.score, &slow.score);
            }
        }
    }

    #[test]
    fn recognizes_the_source_location_of_a_noisy_query() {
        let (map, scenes) = random_map(300, 30, 500, 1);
        for (i, loc) in [0usize, 17, 150, 299].into_iter().enumerate() {
            let q = noisy_query(&scenes[loc], 500, 100 + i as u64);
            let r = recognize_query(&map, &q, Schedule::BestFirst).unwrap();
            assert_eq!(r.location, loc);
            assert!(r.score >= 10, "score {}", r.score);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]
        #[test]
        fn pruned_and_unpruned_searches_agree(seed in 0u64..1000, loc in 0usize..60, vocab in 20u32..200) {
            // Small vocabularies make many locations compete and ties likely.
            let (map, scenes) = random_map(60, 12, vocab, seed);
            let q = noisy_query(&scenes[loc], vocab, seed + 7);
            let ex = recognize_query(&map, &q, Schedule::Exhaustive);
            let ls = recognize_query(&map, &q, Schedule::Lockstep);
            let bf = recognize_query(&map, &q, Schedule::BestFirst);
            let key = |r: Option<Recognition>| r.map(|r| (r.location, r.score));
            prop_assert_eq!(key(ex), key(ls));
            prop_assert_eq!(key(ex), key(bf));
            // And the exhaustive answer is the arg-max of the full score vector.
            let s = scores(&map, &q);
            let best = s.iter().copied().max().unwrap_or(0);
            if let Some(r) = ex {
                prop_assert_eq!(r.score as u32, best);
                prop_assert_eq!(s.iter().position(|&x| x == best), Some(r.location));
            }
            if let (Some(e), Some(b)) = (ex, bf) {
                prop_assert!(b.evaluated <= e.evaluated);
            }
        }

        #[test]
        fn runner_up_is_the_best_score_outside_the_window(seed in 0u64..1000, loc in 0usize..60, vocab in 20u32..200, x in 0usize..6) {
            let (map, scenes) = random_map(60, 12, vocab, seed);
            let q = noisy_query(&scenes[loc], vocab, seed + 7);
            let s = scores(&map, &q);
            let plain = recognize_query(&map, &q, Schedule::BestFirst);
            let with = recognize_with_runner_up(&map, &q, x);
            prop_assert_eq!(plain.map(|r| (r.location, r.score)), with.map(|(r, _)| (r.location, r.score)));
            if let Some((r, runner_up)) = with {
                let outside = s
                    .iter()
                    .enumerate()
                    .filter(|(l, _)| l.abs_diff(r.location) > x)
                    .map(|(_, &v)| v as usize)
                    .max()
                    .unwrap_or(0);
                prop_assert_eq!(runner_up, outside);
            }
        }
    }
}
