"""Measure this machine's single-precision GEMM peak with NumPy/OpenBLAS.

Reference point for `benches/similarity.rs`: seasonloc's cosine matrix must reach at least half
of this throughput. Usage (numpy in a throwaway venv, never a runtime dependency):

    python3 -m venv /tmp/npvenv && /tmp/npvenv/bin/pip install numpy
    /tmp/npvenv/bin/python benches/gemm_peak.py [N | QxDxN ...]

For each shape, times float32 `a @ b.T` with a: Q x N and b: D x N (the cosine matrix's
product; `N` alone means N x N x N), 2·Q·D·N flops, and prints the best and the median of 5
runs. `OPENBLAS_CORETYPE=Haswell` restricts OpenBLAS to AVX2 kernels (what the `gemm` crate
uses on stable Rust) for a like-for-like comparison; `OPENBLAS_VERBOSE=2` prints the kernel.
"""

import os
import sys
import time

import numpy as np


def measure(q: int, d: int, n: int, repeats: int = 5):
    """(best seconds, median seconds) of `a @ b.T` over `repeats` runs."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((q, n), dtype=np.float32)
    b = rng.standard_normal((d, n), dtype=np.float32)
    a @ b.T  # warm-up: thread pool start, page faults
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        a @ b.T
        times.append(time.perf_counter() - t0)
    times.sort()
    return times[0], times[len(times) // 2]


def main() -> None:
    shapes = []
    for arg in sys.argv[1:] or ["4096"]:
        dims = [int(x) for x in arg.split("x")]
        shapes.append(tuple(dims) if len(dims) == 3 else (dims[0],) * 3)
    try:
        from threadpoolctl import threadpool_info  # optional

        threads = [i.get("num_threads") for i in threadpool_info()]
    except ImportError:
        threads = os.environ.get("OPENBLAS_NUM_THREADS", f"default (nproc={os.cpu_count()})")
    print(f"numpy {np.__version__}, BLAS threads: {threads}")
    for q, d, n in shapes:
        best, median = measure(q, d, n)
        flops = 2.0 * q * d * n
        print(
            f"sgemm {q}x{d}x{n}: best {best * 1e3:.1f} ms = {flops / best / 1e9:.1f} GFLOP/s, "
            f"median {median * 1e3:.1f} ms = {flops / median / 1e9:.1f} GFLOP/s"
        )


if __name__ == "__main__":
    main()
