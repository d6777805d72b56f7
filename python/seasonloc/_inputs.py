"""Turning the package's argument forms into what the extension takes: float32 C-contiguous
matrices (converted, or refused with the CLI's message), uint8 images, exclusions, and every
ground-truth form the field uses (read here, interpreted by the core's `GroundTruth`)."""

from __future__ import annotations

import os
from typing import Any, Iterable, List, Optional, Sequence, Tuple, Union

import numpy as np

from . import _native

PathLike = Union[str, "os.PathLike[str]"]


def matrix(x: Any, what: str) -> np.ndarray:
    """`x` as a 2-D C-contiguous float32 array: float or integer data is converted (float64 to
    float32, as the CLI reads `.npy` files), anything else is refused with the CLI's words."""
    a = np.asarray(x)
    if a.dtype.kind not in "fiub":
        raise TypeError(f"{what}: expected float32 or float64 data, got dtype {a.dtype}")
    if a.ndim != 2:
        raise ValueError(f"{what}: expected a 2-D array (Q, D), got shape {list(a.shape)}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{what}: the matrix is empty (shape {a.shape[0]}x{a.shape[1]})")
    return np.ascontiguousarray(a, dtype=np.float32)


def is_path(x: Any) -> bool:
    return isinstance(x, (str, os.PathLike))


def images(x: Any) -> Tuple[Optional[List[str]], Optional[List[np.ndarray]]]:
    """Image inputs as `(paths, None)` or `(None, arrays)`: a folder (its images in file-name
    order, as the CLI takes them), a list of paths, an `N x H x W [x C]` uint8 array or a list
    of `H x W [x C]` uint8 arrays."""
    if is_path(x):
        p = os.fspath(x)
        if os.path.isdir(p):
            return [os.fspath(f) for f in _native.list_images(p)], None
        return [p], None
    if isinstance(x, np.ndarray):
        if x.ndim in (3, 4):  # N gray images, or N colour images
            return None, [_pixels(i, a) for i, a in enumerate(x)]
        if x.ndim == 2:
            return None, [_pixels(0, x)]
        raise ValueError(f"images: expected N x H x W [x C] uint8 pixels, got shape {list(x.shape)}")
    items = list(x)
    if not items:
        raise ValueError("empty input: no images to extract descriptors from")
    if all(is_path(i) for i in items):
        return [os.fspath(i) for i in items], None
    if any(is_path(i) for i in items):
        raise TypeError("images: give either paths or pixel arrays, not both")
    return None, [_pixels(i, a) for i, a in enumerate(items)]


def _pixels(i: int, a: Any) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype != np.uint8:
        raise TypeError(f"image #{i}: expected uint8 pixels (0..255), got dtype {a.dtype}")
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (1, 3, 4))):
        raise ValueError(f"image #{i}: expected an H x W, H x W x 3 or H x W x 4 uint8 array, got shape {list(a.shape)}")
    return np.ascontiguousarray(a)


def exclusions(x: Any) -> Union[None, str, List[Tuple[int, int]]]:
    """`exclude=`: the CLI's text (`"0-16,100-120"`), an index, a `range`, or indices and
    inclusive `(start, end)` pairs."""
    if x is None or isinstance(x, str):
        return x
    if isinstance(x, (int, np.integer)):
        return [(int(x), int(x))]
    if isinstance(x, range) and x.step == 1:
        return [(x.start, x.stop - 1)] if len(x) else []
    out = []
    for item in x:
        if isinstance(item, (int, np.integer)):
            out.append((int(item), int(item)))
        else:
            a, b = item
            out.append((int(a), int(b)))
    return out


def ground_truth(source: Any, *, soft: bool = False, distance: Optional[float] = None) -> "_native.GroundTruth":
    """Any ground-truth form as the core's `GroundTruth` (see `seasonloc.load_ground_truth`)."""
    if isinstance(source, _native.GroundTruth):
        return source
    if is_path(source):
        p = os.fspath(source)
        if os.path.isdir(p):
            db, q = os.path.join(p, "database"), os.path.join(p, "queries")
            if not (os.path.isdir(db) and os.path.isdir(q)):
                raise ValueError(f"{p}: a VPR-methods-evaluation folder has database/ and queries/ sub-folders")
            metres = _native.DEFAULT_POSITIVE_DISTANCE_M if distance is None else distance
            return _native.GroundTruth.from_utm_folders(db, q, float(metres))
        ext = os.path.splitext(p)[1].lower()
        if ext == ".npz":
            with np.load(p) as z:
                key = "GTsoft" if soft else "GThard"
                if key not in z.files:
                    raise ValueError(f"{p}: no `{key}` array (found: {', '.join(z.files)})")
                return _from_array(z[key], p)
        if ext == ".npy":
            # VPR-Bench's ground_truth_new.npy is an object array: a pickle. Load only files you trust.
            return _from_array(np.load(p, allow_pickle=True), p)
        return _native.GroundTruth.from_csv(p)
    if isinstance(source, dict):
        return _native.GroundTruth.from_query_lists([(int(q), _refs(r)) for q, r in source.items()])
    if isinstance(source, np.ndarray):
        return _from_array(source, "ground truth")
    rows = list(source)
    if rows and all(np.ndim(r[1]) == 0 for r in rows):
        return _native.GroundTruth.from_pairs([(int(q), int(r)) for q, r in rows])
    return _native.GroundTruth.from_query_lists([(int(r[0]), _refs(r[1])) for r in rows])


def _refs(r: Any) -> List[int]:
    return [int(v) for v in np.atleast_1d(np.asarray(r, dtype=object)).ravel() if v is not None]


def _from_array(a: np.ndarray, what: str) -> "_native.GroundTruth":
    if a.dtype == object:
        # VPR-Bench: one row per query, [query index, [true reference indices]].
        if a.ndim == 2 and a.shape[1] == 2:
            rows = [(int(r[0]), _refs(r[1])) for r in a]
        else:
            rows = [(int(r[0]), _refs(r[1])) for r in a.ravel()]
        return _native.GroundTruth.from_query_lists(rows)
    if a.ndim != 2:
        raise ValueError(f"{what}: expected a references x queries matrix, (query, ref) pairs or VPR-Bench rows, got shape {list(a.shape)}")
    if a.dtype == bool:
        return _native.GroundTruth.from_match_matrix(np.ascontiguousarray(a))
    if a.dtype.kind in "iu" and a.shape[1] == 2 and not np.isin(a, (0, 1)).all():
        return _native.GroundTruth.from_pairs([(int(q), int(r)) for q, r in a])
    if a.dtype.kind in "iuf" and np.isin(a, (0, 1)).all():
        return _native.GroundTruth.from_match_matrix(np.ascontiguousarray(a != 0))
    raise ValueError(f"{what}: a {a.dtype} array of shape {list(a.shape)} is no ground-truth form "
                     "(a bool references x queries matrix, (query, ref) integer pairs, or VPR-Bench rows)")
