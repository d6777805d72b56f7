//! Trips: latency of one 10-frame batch at trip lengths 100, 1,000 and 10,000 frames on a flat
//! 2,400-image map, and the memory an open trip holds.
//!
//! Input is a descriptor matrix (756-D, the size of HOG with 8 px cells on 64x32 frames), so
//! image decoding and extraction are *not* measured: one iteration is the batch's cosine rows
//! against the map (one GEMM) plus `Trip::push_batch` (online Eq. 2, the `O(D)` row updates,
//! the lag-window re-trace, causal confidences) plus `Trip::to_bytes` (the state the service
//! stores per batch). The trip is advanced to the target length beforehand; every iteration
//! starts from a clone of that state, so the length does not drift.
//!
//! Run: `cargo bench --bench trips -- --warm-up-time 1 --measurement-time 3`.

use criterion::{criterion_group, criterion_main, BatchSize, Criterion};

use seasonloc::similarity::cosine_matrix;
use seasonloc::trip::{column_prior, Trip, TripParams};
use seasonloc::Matrix;

const MAP: usize = 2400;
const DIM: usize = 756;
const BATCH: usize = 10;

/// Deterministic pseudo-random non-negative descriptors (HOG-like: non-negative, unit scale).
fn descriptors(rows: usize, seed: u64) -> Matrix {
    let mut s = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
    let mut m = Matrix::zeros(rows, DIM);
    for v in m.as_mut_slice() {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        *v = ((s >> 40) as f32) / (1u64 << 24) as f32;
    }
    m
}

/// A route-like query: frame `i` is reference `i mod MAP` plus noise.
fn queries(map: &Matrix, first: usize, n: usize, seed: u64) -> Matrix {
    let noise = descriptors(n, seed);
    let mut q = Matrix::zeros(n, DIM);
    for k in 0..n {
        let r = map.row((first + k) % MAP);
        for ((o, a), b) in q.row_mut(k).iter_mut().zip(r).zip(noise.row(k)) {
            *o = a + 0.8 * b;
        }
    }
    q
}

fn batches(c: &mut Criterion) {
    let map = descriptors(MAP, 1);
    let prior = column_prior(&map).expect("non-empty map");
    let mut g = c.benchmark_group("trip_batch_10_frames_map_2400");
    g.sample_size(10);
    let mut trip = Trip::new(prior, TripParams::default()).expect("default parameters");
    for &length in &[100usize, 1_000, 10_000] {
        while trip.frames() < length {
            let q = queries(&map, trip.frames(), 100, trip.frames() as u64);
            let cos = cosine_matrix(&q, &map).expect("same dimension");
            trip.push_batch(&cos).expect("valid batch");
        }
        let bytes = trip.to_bytes();
        eprintln!(
            "trip length {length}: state {} bytes, heap {} bytes",
            bytes.len(),
            trip.heap_bytes()
        );
        let next = queries(&map, length, BATCH, 99);
        g.bench_function(format!("length_{length}"), |b| {
            b.iter_batched(
                || trip.clone(),
                |mut t| {
                    let cos = cosine_matrix(&next, &map).expect("same dimension");
                    let update = t.push_batch(&cos).expect("valid batch");
                    (update, t.to_bytes())
                },
                BatchSize::LargeInput,
            )
        });
    }
    g.finish();
}

criterion_group!(benches, batches);
criterion_main!(benches);
