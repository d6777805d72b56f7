//! The search over all locations for a query's best one (Section II-D), on the elimination
//! of [`super`].
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
//!   and locations whose initial bound is below the winner's score are never built. On the
//!   rayon pool it runs as one best-first search per worker over a round-robin share of the
//!   locations, sharing the best finished score as a bound (same answer; the work done varies
//!   with the workers' timing).
//!
//! Invariant: a location is only ever dropped when its bound (which never increases and is never
//! below its final score) proves it cannot beat or tie-win against the current best.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;

use super::{consistency, Candidates, Elimination, QueryGeometry, Scratch};
use crate::cooc::model::{LocationMap, Word};

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

/// Best-first search: an entity's `J` is only built when its bound (its number of candidate
/// correspondences, then the size of its `J`) is the highest of all. Returns
/// `((score, entity), runner-up, evaluated)`.
///
/// The search covers the candidate groups `g` with `g % shard.1 == shard.0` (one shard:
/// all). With `finished`, the best score any shard has finished is shared: a shard stops when
/// its highest bound falls below it (strictly: an equal bound may still tie-win with a lower
/// entity), and publishes its own answer's score there.
///
/// With `exclusion = Some(x)` the search goes on after the answer until the best entity whose
/// location is more than `x` locations from the answer's finishes: the runner-up score (0 when
/// there is none). Entities near the answer are dropped unbuilt; the bound still prunes the
/// rest, since the first entity to finish outside the window has the highest score there.
fn best_first(
    map: &LocationMap,
    cands: &Candidates,
    geo: &QueryGeometry,
    exclusion: Option<usize>,
    shard: (usize, usize),
    finished: Option<&AtomicUsize>,
) -> (Option<(usize, u32)>, usize, usize) {
    // Groups are in entity order, so `Reverse(group)` breaks ties to the lowest entity.
    let mut heap: BinaryHeap<(usize, Reverse<usize>)> = cands
        .groups
        .iter()
        .enumerate()
        .skip(shard.0)
        .step_by(shard.1.max(1))
        .map(|(g, &(_, s, e))| (e - s, Reverse(g)))
        .collect();
    let beaten = |bound: usize| finished.is_some_and(|f| bound < f.load(Ordering::Relaxed));
    let mut states: Vec<Option<Elimination>> = vec![None; cands.groups.len()];
    let mut scratch = Scratch::default();
    let mut evaluated = 0;
    let mut winner: Option<(usize, u32)> = None;
    while let Some((bound, Reverse(g))) = heap.pop() {
        if beaten(bound) {
            // The highest bound left here cannot reach a score finished elsewhere.
            return (None, 0, evaluated);
        }
        let entity = cands.groups[g].0;
        if let (Some((_, w)), Some(x)) = (winner, exclusion) {
            if map.entity_location(w).abs_diff(map.entity_location(entity)) <= x {
                continue;
            }
        }
        let e = states[g].get_or_insert_with(|| {
            evaluated += 1;
            let mut e = Elimination::default();
            consistency(map, geo, entity, cands.items(g), &mut scratch, &mut e);
            e
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
                if let Some(f) = finished {
                    f.fetch_max(e.bound(), Ordering::Relaxed);
                }
                if exclusion.is_none() {
                    return (winner, 0, evaluated);
                }
                break;
            }
            let key = (e.bound(), Reverse(g));
            if heap.peek().is_some_and(|&top| top > key) || beaten(e.bound()) {
                heap.push(key);
                break;
            }
        }
    }
    (winner, 0, evaluated)
}

/// [`best_first`] on the rayon pool: the candidate groups are dealt round-robin into one shard
/// per worker (neighbouring locations, which share a query's strong candidates, land in
/// different shards), each searched best-first with the best finished score shared as a
/// bound. Every shard's answer is its own best, or it stopped because its bound fell below a
/// score finished elsewhere, so the best of the answers (highest score, ties to the lowest
/// entity) is the sequential search's. Returns `(best, evaluated)`.
fn best_first_parallel(
    map: &LocationMap,
    cands: &Candidates,
    geo: &QueryGeometry,
) -> (Option<(usize, u32)>, usize) {
    let shards = rayon::current_num_threads()
        .min(cands.groups.len() / MIN_GROUPS_PER_SHARD)
        .max(1);
    if shards == 1 {
        let (best, _, evaluated) = best_first(map, cands, geo, None, (0, 1), None);
        return (best, evaluated);
    }
    let finished = AtomicUsize::new(0);
    (0..shards)
        .into_par_iter()
        .map(|k| {
            let (best, _, evaluated) =
                best_first(map, cands, geo, None, (k, shards), Some(&finished));
            (best, evaluated)
        })
        .reduce(
            || (None, 0),
            |(a, ea), (b, eb)| {
                let best = match (a, b) {
                    (Some(x), Some(y)) => Some(if better(y.0, y.1, &Some(x)) { y } else { x }),
                    (x, None) => x,
                    (None, y) => y,
                };
                (best, ea + eb)
            },
        )
}

/// Fewest candidate groups per shard of [`best_first_parallel`]: below this, one sequential
/// search is cheaper than waking the pool.
const MIN_GROUPS_PER_SHARD: usize = 64;

/// The best location for `query` (best-first) and the score of the best location more than
/// `exclusion` locations away from it (0 when none shares a word with the query): the
/// distinctiveness of the answer. `None` when no location shares a visual word with `query`.
pub fn recognize_with_runner_up(
    map: &LocationMap,
    query: &[Word],
    exclusion: usize,
) -> Option<(Recognition, usize)> {
    let geo = QueryGeometry::new(map, query);
    let cands = Candidates::gather(map, query);
    let (best, runner_up, evaluated) = best_first(map, &cands, &geo, Some(exclusion), (0, 1), None);
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
        Schedule::BestFirst => best_first_parallel(map, &Candidates::gather(map, query), &geo),
        Schedule::Exhaustive => {
            // Every entity's `J`, spread over the rayon pool like a full score row; the best
            // (highest score, then lowest entity) is a total order, so the answer does not
            // depend on the order in which the workers finish.
            let cands = Candidates::gather(map, query);
            let best = (0..cands.groups.len())
                .into_par_iter()
                .with_min_len(64)
                .map_init(
                    || (Scratch::default(), Elimination::default()),
                    |(scratch, e), g| {
                        let l = cands.groups[g].0;
                        consistency(map, &geo, l, cands.items(g), scratch, e);
                        (e.run(), l)
                    },
                )
                .reduce_with(|a, b| if better(b.0, b.1, &Some(a)) { b } else { a });
            (best, cands.groups.len())
        }
        Schedule::Lockstep => {
            let cands = Candidates::gather(map, query);
            let mut scratch = Scratch::default();
            let mut live: Vec<(u32, Elimination)> = (0..cands.groups.len())
                .map(|g| {
                    let mut e = Elimination::default();
                    let l = cands.groups[g].0;
                    consistency(map, &geo, l, cands.items(g), &mut scratch, &mut e);
                    (l, e)
                })
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
    use super::super::scores;
    use super::super::tests::{noisy_query, random_map};
    use super::*;
    use proptest::prelude::*;

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
        fn sharded_best_first_gives_the_sequential_answer(seed in 0u64..1000, loc in 0usize..400, vocab in 10u32..120, threads in 2usize..5) {
            // Enough locations for several shards of `MIN_GROUPS_PER_SHARD`; small
            // vocabularies make near-ties between shards likely. A query from the map, or a
            // scene from nowhere (chance scores: ties everywhere).
            let (map, scenes) = random_map(400, 12, vocab, seed);
            let q = if loc % 2 == 0 {
                noisy_query(&scenes[loc], vocab, seed + 3)
            } else {
                random_map(1, 12, vocab, seed + 11).1.remove(0)
            };
            let geo = QueryGeometry::new(&map, &q);
            let cands = Candidates::gather(&map, &q);
            let (sequential, _, _) = best_first(&map, &cands, &geo, None, (0, 1), None);
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let (sharded, _) = pool.install(|| best_first_parallel(&map, &cands, &geo));
            prop_assert!(cands.groups.len() >= 2 * MIN_GROUPS_PER_SHARD);
            prop_assert_eq!(sharded, sequential);
            let ex = recognize_query(&map, &q, Schedule::Exhaustive);
            prop_assert_eq!(sequential.map(|(s, _)| s), ex.map(|r| r.score));
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
