"""Measure this machine's single-precision GEMM peak with NumPy/OpenBLAS.

Reference point for `benches/similarity.rs`: seasonloc's cosine matrix must reach at least half
of this throughput. Usage (numpy in a throwaway venv, never a runtime dependency):

    python3 -m venv /tmp/npvenv && /tmp/npvenv/bin/pip install numpy
    /tmp/npvenv/bin/python benches/gemm_peak.py [N ...]

Prints the best of several runs of float32 `a @ b` (N x N times N x N, 2·N³ flops) per size,
with the thread count OpenBLAS reports.
"""

import os
import sys
import time

import numpy as np


def peak(n: int, repeats: int = 5) -> float:
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, n), dtype=np.float32)
    b = rng.standard_normal((n, n), dtype=np.float32)
    a @ b  # warm-up: thread pool start, page faults
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t0)
    return 2.0 * n**3 / best / 1e9, best


def main() -> None:
    sizes = [int(s) for s in sys.argv[1:]] or [4096]
    try:
        from threadpoolctl import threadpool_info  # optional

        threads = [i.get("num_threads") for i in threadpool_info()]
    except ImportError:
        threads = os.environ.get("OPENBLAS_NUM_THREADS", f"default (nproc={os.cpu_count()})")
    print(f"numpy {np.__version__}, BLAS threads: {threads}")
    for n in sizes:
        gflops, secs = peak(n)
        print(f"sgemm {n}x{n}x{n}: best {secs * 1e3:.1f} ms = {gflops:.1f} GFLOP/s")


if __name__ == "__main__":
    main()
