#!/usr/bin/env python3
"""OpenCV HOGDescriptor timing on the same inputs as `benches/features.rs`, for BENCHMARKS-hog.md.

Single-threaded (cv2.setNumThreads(1)). Cases:
  1. 1024x768 gray image (shared/models/samples/<name>.jpg, gray, resized bilinear), 32 px cells,
     blocks 64x64 with a 32 px stride, 9 bins: the paper's grid, 25,668 values.
  2. a 64x32 Nordland frame, 8 px cells, blocks 16x16 with an 8 px stride: 756 values.
Prints the median and minimum wall time and the mean thread CPU time over many runs (CPU
time and the minimum are the steadier figures on a machine shared with other jobs).

Setup (never a runtime dependency of seasonloc):
    python3 -m venv /tmp/cvenv && /tmp/cvenv/bin/pip install "opencv-python-headless<5" numpy
    (OpenCV 5 no longer exports cv2.HOGDescriptor: the HOG rows are then skipped; 4.14.0 was
    measured for them.)
    /tmp/cvenv/bin/python benches/opencv_hog.py [--image dog] [--runs 200]
Data: ../shared beside the repository, or the folder named by SEASONLOC_SHARED_DIR.
"""
import argparse
import os
import statistics
import sys
import time

import cv2

HERE = os.path.dirname(os.path.abspath(__file__))
SHARED = os.environ.get("SEASONLOC_SHARED_DIR") or os.path.join(HERE, "..", "..", "shared")


def timed(fn, runs):
    """(median wall ms, min wall ms, mean thread-CPU ms) over `runs` calls."""
    fn()  # warm-up
    samples = []
    cpu0 = time.thread_time_ns()
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1e3)
    cpu = (time.thread_time_ns() - cpu0) / 1e6 / runs
    return statistics.median(samples), min(samples), cpu


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--image", default="dog", help="sample name under shared/models/samples")
    ap.add_argument("--runs", type=int, default=200)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(f"opencv {cv2.__version__}, threads {cv2.getNumThreads()}")

    path = os.path.join(SHARED, "models", "samples", args.image + ".jpg")
    if not os.path.exists(path):
        print(f"skipping 1024x768: {path} not found", file=sys.stderr)
    else:
        def prepare():
            g = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
            return cv2.resize(g, (1024, 768), interpolation=cv2.INTER_LINEAR)

        gray = prepare()
        if hasattr(cv2, "HOGDescriptor"):
            hog = cv2.HOGDescriptor((1024, 768), (64, 64), (32, 32), (32, 32), 9)
            dim = hog.compute(gray).size
            med, best, cpu = timed(lambda: hog.compute(gray), args.runs)
            print(f"hog 1024x768 cell 32 ({dim} values): median {med:.3f} ms, min {best:.3f} ms, "
                  f"thread cpu {cpu:.3f} ms")
        else:
            print(f"skipping HOG: OpenCV {cv2.__version__} has no HOGDescriptor", file=sys.stderr)
        med, best, cpu = timed(prepare, max(args.runs // 4, 10))
        print(f"decode+gray+resize {args.image}.jpg -> 1024x768: median {med:.3f} ms, "
              f"min {best:.3f} ms, thread cpu {cpu:.3f} ms")

        # IMREAD_GRAYSCALE above decodes the JPEG's Y plane only (no chroma IDCT, upsampling
        # or colour conversion), like seasonloc's gray decode (`Pixels::Gray`) since issue 16.
        # Below: like for like with seasonloc's colour decode + Rec. 709 luma (the path gray
        # descriptors took before, and the CNN's decode).
        def prepare_colour():
            bgr = cv2.imread(path, cv2.IMREAD_COLOR)
            g = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
            return cv2.resize(g, (1024, 768), interpolation=cv2.INTER_LINEAR)

        med, best, cpu = timed(prepare_colour, max(args.runs // 4, 10))
        print(f"decode colour+cvtColor gray+resize {args.image}.jpg -> 1024x768: median "
              f"{med:.3f} ms, min {best:.3f} ms, thread cpu {cpu:.3f} ms")
        med, best, cpu = timed(lambda: cv2.imread(path, cv2.IMREAD_COLOR), max(args.runs // 4, 10))
        print(f"decode colour only {args.image}.jpg: median {med:.3f} ms, min {best:.3f} ms, "
              f"thread cpu {cpu:.3f} ms")

    # A 4:2:0 camera JPEG (dog.jpg is 4:4:0), as `benches/features.rs` `*_960x540_420`.
    gp = os.path.join(SHARED, "data", "gardenspoint_dev", "day_right", "Image000.jpg")
    if not os.path.exists(gp):
        print(f"skipping 960x540: {gp} not found", file=sys.stderr)
    else:
        for name, flag in [("Y only", cv2.IMREAD_GRAYSCALE), ("colour", cv2.IMREAD_COLOR)]:
            med, best, cpu = timed(lambda: cv2.imread(gp, flag), max(args.runs // 4, 10))
            print(f"decode {name} 960x540 4:2:0: median {med:.3f} ms, min {best:.3f} ms, "
                  f"thread cpu {cpu:.3f} ms")

    frame = os.path.join(SHARED, "data", "nordland_64x32", "summer", "images-05000.png")
    if not os.path.exists(frame):
        print(f"skipping 64x32: {frame} not found", file=sys.stderr)
    else:
        small = cv2.imread(frame, cv2.IMREAD_GRAYSCALE)
        if not hasattr(cv2, "HOGDescriptor"):
            return
        hog = cv2.HOGDescriptor((64, 32), (16, 16), (8, 8), (8, 8), 9)
        dim = hog.compute(small).size
        med, best, cpu = timed(lambda: hog.compute(small), args.runs * 10)
        print(f"hog 64x32 cell 8 ({dim} values): median {med * 1e3:.1f} us, "
              f"min {best * 1e3:.1f} us, thread cpu {cpu * 1e3:.1f} us")


if __name__ == "__main__":
    main()
