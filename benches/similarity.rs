//! Throughput of the cosine similarity matrix (one batched GEMM) and of the column
//! normalisation, on realistic shapes. Throughput is reported in elements/s where one element
//! is one floating-point operation (2·Q·D·N per cosine matrix), i.e. criterion's `Gelem/s`
//! reads as GFLOP/s. Compare with `benches/gemm_peak.py` (NumPy/OpenBLAS SGEMM peak).
//!
//! Run: `cargo bench --bench similarity -- --warm-up-time 1 --measurement-time 3`

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use seasonloc_core::similarity::{cosine_matrix, normalize_columns_in_place};

mod fixture;
use fixture::uniform_matrix;

fn bench_cosine(c: &mut Criterion) {
    let mut group = c.benchmark_group("cosine_matrix");
    group.sample_size(10);
    // (Q, D, N): Nordland with 8 px HOG; a CNN map; a square compute-bound case equal in
    // flops to the 4096³ NumPy reference.
    for (q, d, n) in [(2400, 2400, 756), (2000, 8000, 4096), (4096, 4096, 4096)] {
        let (qm, dm) = (uniform_matrix(q, n, 1), uniform_matrix(d, n, 2));
        group.throughput(Throughput::Elements(2 * (q * d * n) as u64));
        group.bench_with_input(
            BenchmarkId::from_parameter(format!("{q}x{d}x{n}")),
            &(qm, dm),
            |b, (qm, dm)| b.iter(|| cosine_matrix(qm, dm).expect("valid input")),
        );
    }
    group.finish();
}

fn bench_normalize(c: &mut Criterion) {
    let mut group = c.benchmark_group("normalize_columns");
    group.sample_size(10);
    let (q, d) = (2400, 2400);
    let sim = uniform_matrix(q, d, 3);
    group.throughput(Throughput::Elements((q * d) as u64));
    group.bench_function(format!("{q}x{d}"), |b| {
        b.iter_batched_ref(
            || sim.clone(),
            |m| normalize_columns_in_place(m).expect("valid input"),
            criterion::BatchSize::LargeInput,
        )
    });
    group.finish();
}

criterion_group!(benches, bench_cosine, bench_normalize);
criterion_main!(benches);
