#!/usr/bin/env python3
"""onnxruntime anchor for the CNN descriptor timings of BENCHMARKS.md (`benches/cnn.rs`).

The same work as `cnn_nordland400` in `benches/cnn.rs`: the first N Nordland frames (64x32 PNG)
decoded, stretched to 224x224 (bilinear), normalised `(x - 127) / 128`, NCHW, and run through
EfficientNet-Lite0 up to `block10`, on two threads. Two anchor variants, both reported:
  * `intra2`: one session with intra_op_num_threads=2, images one at a time (batch 1);
  * `batch16`: the same session fed batches of 16 images (where the model's batch axis allows).
Prints wall time for the whole set, per image, and the thread split.

Setup (never a runtime dependency of seasonloc):
    python3 -m venv /tmp/perfvenv && /tmp/perfvenv/bin/pip install onnxruntime numpy \
        "opencv-python-headless<5"
    /tmp/perfvenv/bin/python benches/onnxruntime_cnn.py [--frames 400] [--runs 3]
Data: ../shared beside the repository, or the folder named by SEASONLOC_SHARED_DIR.
"""
import argparse
import os
import sys
import time

import cv2
import numpy as np
import onnxruntime as ort

HERE = os.path.dirname(os.path.abspath(__file__))
SHARED = os.environ.get("SEASONLOC_SHARED_DIR") or os.path.join(HERE, "..", "..", "shared")


def prepare(path):
    bgr = cv2.imread(path, cv2.IMREAD_COLOR)
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    x = cv2.resize(rgb, (224, 224), interpolation=cv2.INTER_LINEAR).astype(np.float32)
    x = (x - 127.0) / 128.0
    return np.ascontiguousarray(x.transpose(2, 0, 1))


def session(model, threads):
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(model, so, providers=["CPUExecutionProvider"])


def run_single(sess, paths):
    name = sess.get_inputs()[0].name
    out = []
    for p in paths:
        out.append(sess.run(["block10"], {name: prepare(p)[None]})[0])
    return out


def run_batched(sess, paths, batch):
    name = sess.get_inputs()[0].name
    out = []
    for i in range(0, len(paths), batch):
        x = np.stack([prepare(p) for p in paths[i:i + batch]])
        out.append(sess.run(["block10"], {name: x})[0])
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    model = os.path.join(SHARED, "models", "efficientnet-lite0-224.onnx")
    folder = os.path.join(SHARED, "data", "nordland_64x32", "winter")
    if not (os.path.exists(model) and os.path.isdir(folder)):
        print(f"skipping: {model} or {folder} not found", file=sys.stderr)
        return
    paths = sorted(os.path.join(folder, f) for f in os.listdir(folder) if f.endswith(".png"))
    paths = paths[:args.frames]
    cv2.setNumThreads(1)
    print(f"onnxruntime {ort.__version__}, opencv {cv2.__version__}, {len(paths)} frames, "
          f"intra_op_num_threads={args.threads}")
    sess = session(model, args.threads)
    variants = [("intra2 batch 1", lambda: run_single(sess, paths))]
    # The shipped model may have a fixed batch axis of 1; try a batch of 16 once.
    try:
        run_batched(sess, paths[:16], 16)
        variants.append(("intra2 batch 16", lambda: run_batched(sess, paths, 16)))
    except Exception as e:  # noqa: BLE001 - report and time what works
        print(f"batch 16 not accepted by the model: {str(e).splitlines()[0]}")
    for label, fn in variants:
        fn()  # warm-up (first-run allocations)
        times = []
        for _ in range(args.runs):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        best, med = min(times), sorted(times)[len(times) // 2]
        print(f"{label}: best {best:.3f} s, median {med:.3f} s for {len(paths)} frames "
              f"({best / len(paths) * 1e3:.2f} ms/frame best)")


if __name__ == "__main__":
    main()
