"""Shared fixtures: the CLI binary to compare with, the public datasets (skipped with a clear
message when absent, as the Rust tests do), and generated data."""

import json
import os
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


def _dataset(name, must_have):
    """`$SEASONLOC_DATASETS/NAME`, `data/NAME`, or `shared/data/NAME` one or two levels above
    the repository (crates/test-support's rule)."""
    places = []
    if os.environ.get("SEASONLOC_DATASETS"):
        places.append(Path(os.environ["SEASONLOC_DATASETS"]) / name)
    places.append(REPO / "data" / name)
    places += [REPO / up / "shared" / "data" / name for up in ("..", "../..")]
    for p in places:
        if all((p / m).exists() for m in must_have):
            return p.resolve()
    pytest.skip(f"SKIPPED: dataset {name} not found (looked in {', '.join(map(str, places))}; "
                f"set SEASONLOC_DATASETS to a folder holding {name}/)")


@pytest.fixture(scope="session")
def nordland():
    return _dataset("nordland_64x32", ["summer", "winter", "ground_truth.csv"])


@pytest.fixture(scope="session")
def gardens_point():
    return _dataset("gardenspoint_dev", ["day_right", "night_right", "gt_night_right_vs_day_right.csv"])


@pytest.fixture(scope="session")
def cli():
    """A function running the `seasonloc` binary and returning its JSON (or the failed
    process): `$SEASONLOC_BIN`, else the newest of target/{release,debug}/seasonloc under
    `$CARGO_TARGET_DIR` or the repository."""
    cands = []
    if os.environ.get("SEASONLOC_BIN"):
        cands.append(Path(os.environ["SEASONLOC_BIN"]))
    for root in filter(None, [os.environ.get("CARGO_TARGET_DIR"), str(REPO / "target")]):
        cands += [Path(root) / p / "seasonloc" for p in ("release", "debug")]
    found = [c for c in cands if c.is_file() and os.access(c, os.X_OK)]
    if not found:
        pytest.skip(f"SKIPPED: no seasonloc binary to compare with (looked for {', '.join(map(str, cands))}; "
                    "build it with `cargo build` or set SEASONLOC_BIN)")
    binary = str(found[0]) if os.environ.get("SEASONLOC_BIN") else str(max(found, key=lambda c: c.stat().st_mtime))

    def run(*args, ok=True):
        p = subprocess.run([binary, *map(str, args)], capture_output=True, text=True, timeout=600)
        if not ok:
            return p
        assert p.returncode == 0, p.stderr
        return json.loads(p.stdout)

    return run


def planted(q, d, seed, off=(120, 140)):
    """A Q x D matrix with a route of variable speed planted in noise and a stretch off it."""
    rng = np.random.default_rng(seed)
    S = rng.random((q, d), dtype=np.float32)
    j = 7.0
    for i in range(q):
        if off[0] <= i < off[1]:
            continue
        S[i, min(d - 1, int(j))] += 1.0 + 0.5 * rng.random()
        j += 0.6 + 0.8 * rng.random()
    return S


def write_png(path, pixels):
    """A minimal PNG writer (8-bit gray or RGB) so the tests need nothing beyond numpy."""
    a = np.ascontiguousarray(pixels, dtype=np.uint8)
    h, w = a.shape[:2]
    colour = 2 if a.ndim == 3 else 0
    raw = b"".join(b"\x00" + a[y].tobytes() for y in range(h))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    Path(path).write_bytes(png)


def route_images(n, seed, shift=0, h=32, w=64):
    """`n` RGB frames of a route: frame i shows place i + shift (a blocky texture of its own
    that blends into the next place's), with per-traversal noise, so two calls with different
    seeds are two traversals of one route."""
    rng = np.random.default_rng(1234)
    places = [np.kron(rng.random((h // 4, w // 4)), np.ones((4, 4))) for _ in range(n + shift + 1)]
    noise = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        k = i + shift
        view = (0.8 * places[k] + 0.2 * places[k + 1]) * 200 + noise.random((h, w)) * 30
        rgb = np.stack([view, view * 0.9, view * 0.8], axis=-1)
        frames.append(np.clip(rgb, 0, 255).astype(np.uint8))
    return np.stack(frames)


@pytest.fixture(scope="session")
def route(tmp_path_factory):
    """A generated reference and query traversal as PNG folders, with a CSV ground truth."""
    root = tmp_path_factory.mktemp("route")
    ref, qry = route_images(40, 1), route_images(30, 2, shift=5)
    for name, frames in (("reference", ref), ("query", qry)):
        (root / name).mkdir()
        for i, f in enumerate(frames):
            write_png(root / name / f"frame-{i:03d}.png", f)
    gt = root / "gt.csv"
    gt.write_text("query_index,ref_index\n" + "".join(f"{i},{i + 5}\n" for i in range(30)))
    return {"root": root, "reference": root / "reference", "query": root / "query", "gt": gt,
            "ref_pixels": ref, "query_pixels": qry}
