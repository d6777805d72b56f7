//! Trips: latency of one batch on a flat 2,400-image map (10 frames, at trip lengths 100,
//! 1,000 and 10,000) and on a city-scale 30,790-image map (1 frame and 10 frames, the paper's
//! map size), and the memory an open trip holds.
//!
//! Input is a descriptor matrix (756-D, the size of HOG with 8 px cells on 64x32 frames), so
//! image decoding and extraction are *not* measured: one iteration is the batch's cosine rows
//! against the map normalised beforehand (one GEMM, as the service does with its cached
//! normalised map) plus `Trip::push_batch` (online Eq. 2, the `O(D)` row updates,
//! the lag-window re-trace and confidences) plus `Trip::take_delta` (the state delta the
//! service stores per batch). The `push_only` cases leave the cosine rows out. The trip is advanced to the target length beforehand; every iteration starts from
//! a clone of that state (cloning is not timed), so the length does not drift.
//!
//! Run: `cargo bench --bench trips -- --warm-up-time 1 --measurement-time 3`.

use criterion::{criterion_group, criterion_main, BatchSize, Criterion};

use seasonloc_core::similarity::{cosine_matrix, cosine_matrix_normalized, l2_normalized_rows};
use seasonloc_core::trip::{column_prior, Trip, TripParams};
use seasonloc_core::Matrix;

const DIM: usize = 756;

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

/// A route-like query: frame `i` is reference `i mod D` plus noise.
fn queries(map: &Matrix, first: usize, n: usize, seed: u64) -> Matrix {
    let noise = descriptors(n, seed);
    let mut q = Matrix::zeros(n, DIM);
    for k in 0..n {
        let r = map.row((first + k) % map.rows());
        for ((o, a), b) in q.row_mut(k).iter_mut().zip(r).zip(noise.row(k)) {
            *o = a + 0.8 * b;
        }
    }
    q
}

/// Advances `trip` to `length` frames in batches of 100.
fn advance(trip: &mut Trip, map: &Matrix, length: usize) {
    while trip.frames() < length {
        let n = 100.min(length - trip.frames());
        let q = queries(map, trip.frames(), n, trip.frames() as u64);
        let cos = cosine_matrix(&q, map).expect("same dimension");
        trip.push_batch(&cos).expect("valid batch");
        trip.take_delta();
    }
}

/// One measured batch of `batch` frames after `trip`'s current length.
fn bench_batch(
    g: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>,
    name: String,
    trip: &Trip,
    map: &Matrix,
    batch: usize,
) {
    let next = queries(map, trip.frames(), batch, 99);
    // The service keeps the normalised map per map version (`app::cache`).
    let normalized = l2_normalized_rows(map);
    g.bench_function(name, |b| {
        b.iter_batched(
            || trip.clone(),
            |mut t| {
                let cos = cosine_matrix_normalized(&next, &normalized).expect("same dimension");
                let update = t.push_batch(&cos).expect("valid batch");
                (update, t.take_delta())
            },
            BatchSize::LargeInput,
        )
    });
}

fn report(label: &str, trip: &Trip, map: &Matrix, batch: usize) {
    // Bytes a batch writes: the delta of `batch`-frame batches over 2·lag frames (a snapshot
    // is due once in that span), on a clone.
    let mut t = trip.clone();
    let (mut total, mut n, mut max) = (0usize, 0usize, 0usize);
    while n * batch < 2 * t.params().lag {
        let q = queries(map, t.frames(), batch, 5 + n as u64);
        let cos = cosine_matrix(&q, map).expect("same dimension");
        t.push_batch(&cos).expect("valid batch");
        let bytes = t.take_delta().bytes();
        (total, max, n) = (total + bytes, max.max(bytes), n + 1);
    }
    let stored = t.stored_state();
    eprintln!(
        "{label}: batch of {batch} writes {} bytes on average (max {max}), stored form {} bytes, heap {} bytes",
        total / n,
        stored.base.len() + stored.snapshot.len() + stored.log.iter().map(|(_, r)| r.len()).sum::<usize>(),
        trip.heap_bytes()
    );
}

fn batches(c: &mut Criterion) {
    let map = descriptors(2400, 1);
    let prior = column_prior(&map).expect("non-empty map");
    let mut g = c.benchmark_group("trip_batch_10_frames_map_2400");
    g.sample_size(10);
    let mut trip = Trip::new(prior, TripParams::default()).expect("default parameters");
    for &length in &[100usize, 1_000, 10_000] {
        advance(&mut trip, &map, length);
        report(&format!("map 2400, length {length}"), &trip, &map, 10);
        bench_batch(&mut g, format!("length_{length}"), &trip, &map, 10);
    }
    g.finish();
}

fn city(c: &mut Criterion) {
    let map = descriptors(30_790, 7);
    let prior = column_prior(&map).expect("non-empty map");
    let mut g = c.benchmark_group("trip_map_30790");
    g.sample_size(10);
    let mut trip = Trip::new(prior, TripParams::default()).expect("default parameters");
    advance(&mut trip, &map, 200);
    report("map 30790, length 200", &trip, &map, 1);
    for batch in [1usize, 10] {
        bench_batch(
            &mut g,
            format!("batch_{batch}_length_200"),
            &trip,
            &map,
            batch,
        );
    }
    // The trip alone (its cosine rows computed beforehand): what `push_batch` and the
    // delta cost.
    for batch in [1usize, 10] {
        let q = queries(&map, trip.frames(), batch, 99);
        let cos = cosine_matrix(&q, &map).expect("same dimension");
        g.bench_function(format!("push_only_batch_{batch}_length_200"), |b| {
            b.iter_batched(
                || trip.clone(),
                |mut t| {
                    let update = t.push_batch(&cos).expect("valid batch");
                    (update, t.take_delta())
                },
                BatchSize::LargeInput,
            )
        });
    }
    g.finish();
}

criterion_group!(benches, batches, city);
criterion_main!(benches);
