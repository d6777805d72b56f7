"""The GIL benchmark: one solve of a 2000 x 8000 matrix against two solves in two Python
threads at once, each on one core (RAYON_NUM_THREADS=1). With the GIL released during the
work, the two threads take about the time of one on a machine with two free cores.

usage: python python/bench/gil.py [--repeat 3]   (after `pip install ./python`)
Prints one line per measurement and the ratio; BENCHMARKS.md records the figure."""

import os

os.environ.setdefault("RAYON_NUM_THREADS", "1")

import argparse  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import seasonloc as sl  # noqa: E402


def planted(q, d, seed):
    rng = np.random.default_rng(seed)
    S = rng.random((q, d), dtype=np.float32)
    j = 7.0
    for i in range(q):
        S[i, min(d - 1, int(j))] += 1.0 + 0.5 * rng.random()
        j += 0.6 + 0.8 * rng.random()
    return S


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    A, B = planted(2000, 8000, 11), planted(2000, 8000, 12)
    sl.solve(planted(50, 80, 1))
    one = []
    for _ in range(args.repeat):
        t = time.perf_counter()
        sl.solve(A, fan_out=4)
        one.append(time.perf_counter() - t)
    two = []
    for _ in range(args.repeat):
        ts = [threading.Thread(target=sl.solve, args=(M,), kwargs={"fan_out": 4}) for M in (A, B)]
        t = time.perf_counter()
        for th in ts:
            th.start()
        for th in ts:
            th.join()
        two.append(time.perf_counter() - t)
    print(f"one solve (2000 x 8000, RAYON_NUM_THREADS={os.environ['RAYON_NUM_THREADS']}): "
          f"min {min(one):.3f} s of {args.repeat}")
    print(f"two solves in two threads at once: min {min(two):.3f} s of {args.repeat}")
    print(f"ratio {min(two) / min(one):.2f}x (1.0 = perfectly parallel, 2.0 = serialised by the GIL); "
          f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
