//! The visual vocabulary: a vocabulary tree (hierarchical k-means, Nistér & Stewénius 2006),
//! an approximate k-means whose leaves are the visual words.
//!
//! Why a tree: a flat k-means with `k = b^L` words costs `k` distance computations per descriptor
//! for both training and quantisation; the tree costs `b * L` (30 instead of 1,000 for the
//! default 10^3 words), which keeps vocabulary training under a few seconds on two cores and
//! quantisation negligible next to feature extraction.
//!
//! Invariants: every internal node has between 2 and `b` children; words are numbered
//! `0..len()` in depth-first order of the leaves; [`Vocabulary::quantize`] is deterministic and
//! always returns a valid word. Training is deterministic for a given seed.

use rayon::prelude::*;

use super::SplitMix64;
use crate::{Error, Result};

/// A trained vocabulary tree.
#[derive(Clone, Debug, PartialEq)]
pub struct Vocabulary {
    pub(crate) dim: usize,
    /// Node centroids, `nodes * dim` values (the root's is unused and zero).
    pub(crate) centroids: Vec<f32>,
    /// Per node: first child index and child count (count 0 = leaf).
    pub(crate) children: Vec<(u32, u32)>,
    /// Per node: its word if it is a leaf, `u32::MAX` otherwise.
    pub(crate) leaf_word: Vec<u32>,
    pub(crate) words: u32,
}

/// Training settings of [`Vocabulary::train`].
#[derive(Clone, Copy, Debug)]
pub struct TreeSpec {
    /// Children per node.
    pub branching: usize,
    /// Levels below the root.
    pub depth: usize,
    /// Lloyd iterations per node.
    pub iterations: usize,
    /// Seed of k-means++ initialisation.
    pub seed: u64,
}

impl Vocabulary {
    /// Trains a tree on `data` (`n * dim` values, one descriptor per row).
    pub fn train(data: &[f32], dim: usize, spec: TreeSpec) -> Result<Self> {
        if data.len().checked_rem(dim) != Some(0) {
            return Err(Error::Shape(format!(
                "{} training values are not a whole number of {dim}-D descriptors",
                data.len()
            )));
        }
        let n = data.len() / dim;
        if n < 2 {
            return Err(Error::Empty(format!(
                "vocabulary training needs at least 2 descriptors, got {n}"
            )));
        }
        if let Some(k) = data.iter().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite {
                what: "vocabulary training descriptors",
                row: k / dim,
                col: k % dim,
                value: f64::from(data[k]),
            });
        }
        let mut voc = Vocabulary {
            dim,
            centroids: vec![0.0; dim],
            children: vec![(0, 0)],
            leaf_word: vec![u32::MAX],
            words: 0,
        };
        let mut rng = SplitMix64::new(spec.seed);
        let all: Vec<u32> = (0..n as u32).collect();
        voc.grow(0, &all, data, spec, 0, &mut rng);
        voc.number_leaves();
        Ok(voc)
    }

    /// Number of visual words.
    pub fn len(&self) -> usize {
        self.words as usize
    }

    /// True when the vocabulary has no words (never for a trained one).
    pub fn is_empty(&self) -> bool {
        self.words == 0
    }

    /// Descriptor length.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// The visual word of one descriptor (greedy descent of the tree).
    pub fn quantize(&self, desc: &[f32]) -> u32 {
        debug_assert_eq!(desc.len(), self.dim);
        let mut node = 0usize;
        loop {
            let (first, count) = self.children[node];
            if count == 0 {
                return self.leaf_word[node];
            }
            let mut best = (f32::INFINITY, first as usize);
            for c in first as usize..(first + count) as usize {
                let d = sq_dist(desc, &self.centroids[c * self.dim..(c + 1) * self.dim]);
                if d < best.0 {
                    best = (d, c);
                }
            }
            node = best.1;
        }
    }

    fn grow(
        &mut self,
        node: usize,
        members: &[u32],
        data: &[f32],
        spec: TreeSpec,
        level: usize,
        rng: &mut SplitMix64,
    ) {
        if level == spec.depth || members.len() <= spec.branching {
            return;
        }
        let centers = kmeans(
            members,
            data,
            self.dim,
            spec.branching,
            spec.iterations,
            rng,
        );
        let assign = assign(members, data, self.dim, &centers);
        let k = centers.len() / self.dim;
        let mut groups: Vec<Vec<u32>> = vec![Vec::new(); k];
        for (&m, &a) in members.iter().zip(&assign) {
            groups[a as usize].push(m);
        }
        let kept: Vec<usize> = (0..k).filter(|&c| !groups[c].is_empty()).collect();
        if kept.len() < 2 {
            return; // all members identical: stay a leaf
        }
        let first = self.children.len();
        for &c in &kept {
            self.centroids
                .extend_from_slice(&centers[c * self.dim..(c + 1) * self.dim]);
            self.children.push((0, 0));
            self.leaf_word.push(u32::MAX);
        }
        self.children[node] = (first as u32, kept.len() as u32);
        for (i, &c) in kept.iter().enumerate() {
            self.grow(first + i, &groups[c], data, spec, level + 1, rng);
        }
    }

    /// Numbers the leaves depth-first so words of one subtree are contiguous.
    fn number_leaves(&mut self) {
        let mut stack = vec![0usize];
        let mut next = 0u32;
        while let Some(node) = stack.pop() {
            let (first, count) = self.children[node];
            if count == 0 {
                self.leaf_word[node] = next;
                next += 1;
            } else {
                stack.extend((first..first + count).rev().map(|c| c as usize));
            }
        }
        self.words = next;
    }

    /// Checks the structural invariants (used after decoding untrusted bytes).
    pub(crate) fn check(&self) -> Result<()> {
        let nodes = self.children.len();
        let bad = |reason: String| Err(Error::Shape(format!("vocabulary tree: {reason}")));
        if nodes == 0 || self.centroids.len() != nodes * self.dim || self.leaf_word.len() != nodes {
            return bad(format!("{nodes} nodes with inconsistent arrays"));
        }
        let mut seen = vec![false; self.words as usize];
        for (i, &(first, count)) in self.children.iter().enumerate() {
            if count == 0 {
                let w = self.leaf_word[i];
                if w >= self.words || std::mem::replace(&mut seen[w as usize], true) {
                    return bad(format!("leaf {i} has invalid or repeated word {w}"));
                }
            } else if first as usize <= i || (first + count) as usize > nodes {
                return bad(format!("node {i} has children {first}..{}", first + count));
            }
        }
        if seen.iter().any(|s| !s) || self.centroids.iter().any(|v| !v.is_finite()) {
            return bad("missing words or non-finite centroids".into());
        }
        Ok(())
    }
}

#[inline]
fn sq_dist(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// Index of the nearest centre of each member (parallel over members).
fn assign(members: &[u32], data: &[f32], dim: usize, centers: &[f32]) -> Vec<u32> {
    members
        .par_iter()
        .with_min_len(256)
        .map(|&m| {
            let x = &data[m as usize * dim..(m as usize + 1) * dim];
            let mut best = (f32::INFINITY, 0u32);
            for (c, centre) in centers.chunks_exact(dim).enumerate() {
                let d = sq_dist(x, centre);
                if d < best.0 {
                    best = (d, c as u32);
                }
            }
            best.1
        })
        .collect()
}

/// k-means++ seeding followed by Lloyd iterations; empty clusters keep their old centre.
fn kmeans(
    members: &[u32],
    data: &[f32],
    dim: usize,
    k: usize,
    iterations: usize,
    rng: &mut SplitMix64,
) -> Vec<f32> {
    let row = |m: u32| &data[m as usize * dim..(m as usize + 1) * dim];
    let mut centers: Vec<f32> = Vec::with_capacity(k * dim);
    centers.extend_from_slice(row(members[rng.below(members.len())]));
    let mut d2: Vec<f32> = members
        .iter()
        .map(|&m| sq_dist(row(m), &centers[..dim]))
        .collect();
    while centers.len() < k * dim {
        let total: f64 = d2.iter().map(|&v| f64::from(v)).sum();
        if total <= 0.0 {
            break; // fewer distinct points than k
        }
        let mut target = rng.next_f64() * total;
        let mut pick = members.len() - 1;
        for (i, &v) in d2.iter().enumerate() {
            target -= f64::from(v);
            if target <= 0.0 {
                pick = i;
                break;
            }
        }
        let start = centers.len();
        centers.extend_from_slice(row(members[pick]));
        let c = centers[start..].to_vec();
        for (i, &m) in members.iter().enumerate() {
            d2[i] = d2[i].min(sq_dist(row(m), &c));
        }
    }
    let k = centers.len() / dim;
    for _ in 0..iterations {
        let a = assign(members, data, dim, &centers);
        let mut sums = vec![0.0f64; k * dim];
        let mut counts = vec![0usize; k];
        for (&m, &c) in members.iter().zip(&a) {
            counts[c as usize] += 1;
            for (s, &v) in sums[c as usize * dim..(c as usize + 1) * dim]
                .iter_mut()
                .zip(row(m))
            {
                *s += f64::from(v);
            }
        }
        for c in 0..k {
            if counts[c] > 0 {
                for d in 0..dim {
                    centers[c * dim + d] = (sums[c * dim + d] / counts[c] as f64) as f32;
                }
            }
        }
    }
    centers
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(branching: usize, depth: usize) -> TreeSpec {
        TreeSpec {
            branching,
            depth,
            iterations: 10,
            seed: 3,
        }
    }

    /// `clusters` tight 4-D blobs of `per` points each around well-separated centres.
    fn blobs(clusters: usize, per: usize) -> Vec<f32> {
        let mut rng = SplitMix64::new(11);
        let mut data = Vec::new();
        for c in 0..clusters {
            for _ in 0..per {
                for d in 0..4 {
                    let centre = if d == c % 4 {
                        10.0 * (1 + c / 4) as f32
                    } else {
                        0.0
                    };
                    data.push(centre + (rng.next_f64() as f32 - 0.5) * 0.1);
                }
            }
        }
        data
    }

    #[test]
    fn separates_well_separated_blobs() {
        let data = blobs(8, 30);
        let voc = Vocabulary::train(&data, 4, spec(8, 1)).unwrap();
        assert_eq!(voc.len(), 8);
        // Points of one blob share a word, different blobs get different words.
        let words: Vec<u32> = data.chunks_exact(4).map(|x| voc.quantize(x)).collect();
        for c in 0..8 {
            let w = &words[c * 30..(c + 1) * 30];
            assert!(w.iter().all(|&x| x == w[0]), "blob {c} split: {w:?}");
        }
        let mut firsts: Vec<u32> = (0..8).map(|c| words[c * 30]).collect();
        firsts.sort_unstable();
        firsts.dedup();
        assert_eq!(firsts.len(), 8);
    }

    #[test]
    fn tree_has_at_most_b_to_the_l_words_and_passes_its_check() {
        let data = blobs(16, 20);
        let voc = Vocabulary::train(&data, 4, spec(3, 2)).unwrap();
        assert!(voc.len() <= 9 && voc.len() >= 2, "{} words", voc.len());
        voc.check().unwrap();
        for x in data.chunks_exact(4) {
            assert!((voc.quantize(x) as usize) < voc.len());
        }
    }

    #[test]
    fn training_is_deterministic() {
        let data = blobs(12, 10);
        let a = Vocabulary::train(&data, 4, spec(4, 2)).unwrap();
        let b = Vocabulary::train(&data, 4, spec(4, 2)).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn identical_points_give_one_word() {
        let data = vec![1.0f32; 4 * 50];
        let voc = Vocabulary::train(&data, 4, spec(5, 3)).unwrap();
        assert_eq!(voc.len(), 1);
    }

    #[test]
    fn rejects_bad_training_input() {
        assert!(matches!(
            Vocabulary::train(&[1.0; 7], 4, spec(2, 1)),
            Err(Error::Shape(_))
        ));
        let mut data = blobs(2, 5);
        data[9] = f32::NAN;
        assert!(matches!(
            Vocabulary::train(&data, 4, spec(2, 1)),
            Err(Error::NonFinite { row: 2, col: 1, .. })
        ));
    }
}
