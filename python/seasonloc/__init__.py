"""seasonloc for Python: visual localization on a route across seasons, on NumPy arrays.

The same core code as the `seasonloc` command line (a thin PyO3 binding, no second
implementation): descriptors (`hog`, `cnn`), the similarity matrix (`similarity`), the
flow graph with its confidences (`solve`, `localize`), the baselines (`best_match`,
`seqslam`), the evaluation with the field's metrics and ground-truth forms (`evaluate`,
`load_ground_truth`) and the online `Trip`. Every call that computes releases the GIL.

Bad input raises `ValueError` / `TypeError` (an unreadable file `OSError`) with the message the
CLI prints. Guide: docs/python.md in the repository.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from . import _inputs, _native
from ._native import GroundTruth

__version__: str = _native.__version__

__all__ = [
    "Prediction", "Match", "RowAssignment", "Hypothesis", "Solution", "Evaluation", "Estimate",
    "GroundTruth", "similarity", "solve", "localize", "hog", "cnn", "best_match", "seqslam",
    "cooc", "evaluate", "load_ground_truth", "recall_at_n", "Trip", "STANDARD_NS",
]

#: The N of Recall@N reported by default (VPR-methods-evaluation's, up to 20).
STANDARD_NS: Tuple[int, ...] = tuple(_native.STANDARD_NS)
_SEQSLAM_DEFAULTS, _DEFAULT_DISCOUNT, _MAX_TOLERANCE = _native.defaults()


@dataclass(frozen=True)
class Prediction:
    """One method's answer for one query: reference `ref` with `confidence` (higher = more
    certain; the method's own scale) and, for the calibrated flow methods, `p_correct`, the
    probability that `ref` is within the tolerance of the true place."""

    query: int
    ref: int
    confidence: float
    p_correct: Optional[float] = None


@dataclass(frozen=True)
class Match:
    """A matched reference of a hypothesis' row, with the similarity the graph saw."""

    ref: int
    similarity: float


@dataclass(frozen=True)
class RowAssignment:
    """What a hypothesis says about one query row: its matches (empty when hidden)."""

    query: int
    matches: List[Match]


@dataclass(frozen=True)
class Hypothesis:
    """A route hypothesis (one source-to-sink path of the graph), 1-based `rank`."""

    rank: int
    cost: float
    rows: List[RowAssignment]


@dataclass
class Solution:
    """The result of `solve` / `localize`: the ranked hypotheses, at most one prediction per
    query, the costs, and the similarity matrix the queries are rows of (`solve`: the matrix
    given; `localize`: the raw cosine matrix C), which `evaluate` ranks for Recall@N."""

    predictions: List[Prediction]
    hypotheses: List[Hypothesis]
    total_cost: float
    hidden_cost: float
    similarity: np.ndarray = field(repr=False)

    @property
    def num_queries(self) -> int:
        """Query rows of the similarity matrix."""
        return int(self.similarity.shape[0])

    def to_dict(self) -> Dict[str, Any]:
        """The CLI's `seasonloc solve` JSON shape."""
        return {
            "total_cost": self.total_cost,
            "hidden_cost": self.hidden_cost,
            "hypotheses": [{"rank": h.rank, "cost": h.cost, "rows": [
                {"query": r.query, "matches": [{"ref": m.ref, "similarity": m.similarity} for m in r.matches]}
                for r in h.rows]} for h in self.hypotheses],
            "predictions": [{k: v for k, v in (("query", p.query), ("ref", p.ref), ("confidence", p.confidence),
                                               ("p_correct", p.p_correct)) if v is not None} for p in self.predictions],
        }


@dataclass(frozen=True)
class Evaluation:
    """The metrics of `evaluate`: seasonloc's (`ap`, `recall_at_100p`, `recall_at_99p`,
    `max_f1`, `precision_at_full`), the field's (`recall_at_n` {N: recall} when a similarity
    matrix is known, `auc` as VPR_Tutorial computes it), the counts behind them and the PR
    `curve` [(threshold, precision, recall)]. Definitions: docs/metrics.md."""

    ap: float
    auc: float
    recall_at_100p: float
    recall_at_99p: float
    max_f1: float
    precision_at_full: float
    positives: int
    predicted: int
    correct: int
    recall_at_n: Dict[int, float]
    curve: List[Tuple[float, float, float]] = field(repr=False)

    def to_dict(self) -> Dict[str, Any]:
        """Flat: the metrics as `seasonloc eval` names them, plus `recall@N` per N."""
        d: Dict[str, Any] = {k: getattr(self, k) for k in (
            "ap", "auc", "recall_at_100p", "recall_at_99p", "max_f1", "precision_at_full",
            "positives", "predicted", "correct")}
        d.update({f"recall@{n}": r for n, r in self.recall_at_n.items()})
        return d


def _predictions(rows) -> List[Prediction]:
    return [Prediction(int(q), int(r), float(c), None if p is None else float(p)) for q, r, c, p in rows]


def _solution(solved, similarity: np.ndarray) -> Solution:
    total, hidden, hyps, preds = solved
    hypotheses = [Hypothesis(rank, cost, [RowAssignment(q, [Match(r, s) for r, s in ms]) for q, ms in rows])
                  for rank, cost, rows in hyps]
    return Solution(_predictions(preds), hypotheses, total, hidden, similarity)


def _hidden_cost(w: Union[str, float, None]) -> Optional[float]:
    if w is None or (isinstance(w, str) and w.lower() == "auto"):
        return None
    if isinstance(w, str):
        raise ValueError(f"invalid parameter `hidden_cost`: expected `auto` or a finite number > 0, got `{w}`")
    return float(w)


def _normalization(normalize: Union[bool, str]) -> str:
    if normalize is True:
        return "floored"
    if normalize is False or normalize is None:
        return "none"
    return str(normalize)


def similarity(ref: Any, query: Any, normalize: Union[bool, str] = True) -> np.ndarray:
    """The Q x D similarity matrix of `query` (Q x N descriptors) against `ref` (D x N): the
    cosine matrix C (Eq. 1), then with `normalize=True` the column normalisation of `eval` and
    `localize` (Eq. 2 with the column mean floored at half the median, `"floored"`); `"eq2"`
    is the paper's Eq. 2 exactly, `False` / `"none"` leaves C raw. float32."""
    r = _inputs.matrix(ref, "reference descriptors")
    q = _inputs.matrix(query, "query descriptors")
    return _native.similarity(r, q, _normalization(normalize))


def solve(S: Any, fan_out: int = 4, hidden_cost: Union[str, float] = "auto", flows: int = 1,
          exact: bool = False, *, horizontal: bool = True, stop_hidden_fraction: Optional[float] = None,
          normalize: bool = False, tolerance: int = 1) -> Solution:
    """`seasonloc solve` on a Q x D similarity matrix (queries as rows): the data-association
    graph with fan-out `fan_out`, hidden cost `hidden_cost` (`"auto"` or a number > 0), `flows`
    route hypotheses (greedy, or an exact min-cost flow with `exact`). `S` is used as the
    normalised similarity ĉ directly unless `normalize` (then it is the raw cosine matrix and
    gets Eq. 2 first), exactly as the CLI's `--normalize`. Returns a `Solution` whose
    predictions carry their confidence and `p_correct` at `tolerance` frames."""
    m = _inputs.matrix(S, "similarity matrix")
    solved = _native.solve(m, int(fan_out), _hidden_cost(hidden_cost), int(flows), bool(exact),
                           bool(horizontal), stop_hidden_fraction, bool(normalize), int(tolerance))
    return _solution(solved, m)


def localize(ref_desc: Any, query_desc: Any, *, fan_out: int = 4, hidden_cost: Union[str, float] = "auto",
             flows: int = 1, exact: bool = False, horizontal: bool = True,
             stop_hidden_fraction: Optional[float] = None, normalization: str = "floored",
             claim: Optional[int] = None, tolerance: int = 1, confidence: str = "discounted",
             confidence_radius: int = 2, confidence_discount: float = _DEFAULT_DISCOUNT) -> Solution:
    """The flow method of `seasonloc eval` on descriptors (one row per image; references in
    route order, queries in driving order): C (Eq. 1), `normalization` (`"floored"`, `"eq2"`,
    `"none"`), the graph, and per query the confidence with `claim` frames (default:
    `tolerance`, as `eval`) and `p_correct` at `tolerance`. `confidence="window"` is the 11-row
    box window of earlier versions. The `Solution`'s `similarity` is C (for Recall@N)."""
    r = _inputs.matrix(ref_desc, "reference descriptors")
    q = _inputs.matrix(query_desc, "query descriptors")
    if confidence not in ("discounted", "window"):
        raise ValueError(f"invalid parameter `confidence`: expected `discounted` or `window`, got `{confidence}`")
    discount = float(confidence_discount) if confidence == "discounted" else None
    solved, c = _native.localize(r, q, int(fan_out), _hidden_cost(hidden_cost), int(flows), bool(exact),
                                 bool(horizontal), stop_hidden_fraction, str(normalization),
                                 int(tolerance if claim is None else claim), int(tolerance),
                                 int(confidence_radius), discount)
    return _solution(solved, c)


def hog(images: Any, cell_size: int = 32, *, resize: Optional[Tuple[int, int]] = None,
        fit: str = "stretch") -> np.ndarray:
    """HOG descriptors (one row per image, float32) on a dense grid of `cell_size` px cells, as
    `seasonloc eval --cell-size`. `images`: a folder (its images in file-name order), a list of
    paths, a list of H x W [x 3|4] uint8 arrays, or an N x H x W (gray) / N x H x W x C array.
    Every image is brought to `resize` (width, height) or the first image's size by `fit`
    (`"stretch"` or `"crop"`)."""
    paths, arrays = _inputs.images(images)
    size = None if resize is None else (int(resize[0]), int(resize[1]))
    if paths is not None:
        return _native.hog_files(paths, int(cell_size), size, fit)
    return _native.hog_arrays(arrays, int(cell_size), size, fit)


def cnn(images: Any, model: str, *, layer: str = "block10", input_size: Tuple[int, int] = (224, 224),
        resize: str = "stretch", short_side: Optional[int] = None,
        mean: Sequence[float] = (127.0, 127.0, 127.0), scale: Sequence[float] = (128.0, 128.0, 128.0)) -> np.ndarray:
    """CNN descriptors (one row per image, float32): output `layer` of the ONNX model at
    `model`, flattened and L2-normalised, as `seasonloc eval --descriptor cnn` with its
    `--cnn-*` defaults. `images` as for `hog`; `resize` `"stretch"` or `"crop"` (short side
    `short_side`, then the centre); pixels become `(x - mean) / scale` per R, G, B."""
    if not getattr(_native, "HAS_CNN", False):
        raise RuntimeError("this build of seasonloc has no CNN support (built without the `cnn` feature)")
    if resize not in ("stretch", "crop"):
        raise ValueError(f"invalid parameter `resize`: expected `stretch` or `crop`, got `{resize}`")
    paths, arrays = _inputs.images(images)
    triple = lambda v: [float(x) for x in (v if np.ndim(v) else [v] * 3)]  # noqa: E731
    return _native.cnn(paths, arrays, str(model), str(layer), (int(input_size[0]), int(input_size[1])),
                       resize == "crop", short_side, triple(mean), triple(scale))


def best_match(C: Any) -> List[Prediction]:
    """The best-match baseline: per query row of `C` (Q x D) the most similar reference, with
    that similarity as confidence (rows whose best value is <= 0 give none)."""
    return _predictions(_native.best_match(_inputs.matrix(C, "similarity matrix")))


def seqslam(C: Any, *, ds: int = _SEQSLAM_DEFAULTS[0], enhance_window: int = _SEQSLAM_DEFAULTS[1],
            v_min: float = _SEQSLAM_DEFAULTS[2], v_max: float = _SEQSLAM_DEFAULTS[3],
            v_step: float = _SEQSLAM_DEFAULTS[4], exclusion_window: int = _SEQSLAM_DEFAULTS[5]) -> List[Prediction]:
    """SeqSLAM (Milford & Wyeth 2012, as OpenSeqSLAM, whose parameters are the defaults) on the
    raw cosine matrix `C` (Q x D): the difference matrix 1 - C, contrast enhancement, straight
    trajectories; confidence is its uniqueness ratio."""
    rows = _native.seqslam(_inputs.matrix(C, "similarity matrix"), int(ds), int(enhance_window),
                           float(v_min), float(v_max), float(v_step), int(exclusion_window))
    return _predictions(rows)


def cooc(reference_images: Any, query_images: Any, method: str = "cooc", *, tolerance: int = 0) -> List[Prediction]:
    """The co-occurrence method (Johns & Yang, feature co-occurrence maps) on images, as
    `seasonloc eval --method cooc|cooc-seq|cooc-flow` with its default parameters: a map of the
    reference images (one mapping drive, in route order; image k = location k), the query images
    localized by `method`: `"cooc"` (single image), `"cooc-seq"` (the paper's sequences) or
    `"cooc-flow"` (the co-occurrence scores in the flow graph, claim = `tolerance`). Images as
    for `hog` (they are used in gray)."""
    rp, ra = _inputs.images(reference_images)
    qp, qa = _inputs.images(query_images)
    return _predictions(_native.cooc(rp, ra, qp, qa, str(method), int(tolerance)))


def load_ground_truth(source: Any, *, soft: bool = False, distance: Optional[float] = None) -> GroundTruth:
    """A ground truth from any of the field's forms:

    - a CSV path (header with `query_index`, `ref_index`; seasonloc's and the CLI's form);
    - VPR-Bench's `ground_truth_new.npy` (path or loaded object array): one row per query,
      `[query index, [true reference indices]]` (a pickle: load only files you trust);
    - VPR_Tutorial's `GThard` / `GTsoft`: a bool references x queries matrix, its `.npy`, or a
      `.npz` holding `GThard` (`GTsoft` with `soft=True`);
    - VPR-methods-evaluation's folder layout: a folder with `database/` and `queries/` whose
      file names carry UTM coordinates (`@east@north@...`), true within `distance` metres
      (default 25);
    - a dict {query: [refs]}, a list of (query, ref) pairs, or a `GroundTruth`."""
    return _inputs.ground_truth(source, soft=soft, distance=distance)


def _prediction_triples(preds: Any) -> List[Tuple[int, int, float]]:
    out = []
    for p in preds:
        if isinstance(p, Prediction):
            out.append((p.query, p.ref, p.confidence))
        elif isinstance(p, dict):
            r = p.get("ref", p.get("ref_index"))
            if r is None:
                continue
            out.append((int(p.get("query", p.get("query_index"))), int(r), float(p["confidence"])))
        else:
            q, r, c = tuple(p)[:3]
            if r is None:
                continue
            out.append((int(q), int(r), float(c)))
    return out


def evaluate(predictions: Any, ground_truth: Any, tolerance: int = 0, *, exclude: Any = None,
             num_queries: Optional[int] = None, similarity: Any = None,
             ns: Sequence[int] = STANDARD_NS, soft: bool = False) -> Evaluation:
    """Scores predictions against a ground truth as `seasonloc eval` does (a prediction is right
    within `tolerance` reference frames of a true match; `exclude` leaves queries out: the
    CLI's text such as `"0-16"`, indices, a range or (start, end) pairs), and adds the field's
    metrics: Recall@N for each of `ns` from the ranking of a similarity matrix (queries as rows)
    and the PR curve's AUC as VPR_Tutorial computes it.

    `predictions`: a `Solution` (its `similarity` then gives Recall@N), a list of `Prediction`,
    of {query, ref, confidence} dicts or of (query, ref, confidence) tuples, or a similarity
    matrix itself (scored by its best match per query, ranked for Recall@N).
    `ground_truth`: any form `load_ground_truth` reads. `num_queries` (the recall denominator's
    range) defaults to the similarity matrix's rows, else the largest query index seen + 1."""
    gt = _inputs.ground_truth(ground_truth, soft=soft)
    sim = None if similarity is None else _inputs.matrix(similarity, "similarity matrix")
    if isinstance(predictions, Solution):
        sim = predictions.similarity if sim is None else sim
        triples = _prediction_triples(predictions.predictions)
    elif isinstance(predictions, np.ndarray) and predictions.ndim == 2 and predictions.dtype.kind in "fiub":
        m = _inputs.matrix(predictions, "similarity matrix")
        sim = m if sim is None else sim
        triples = _prediction_triples(best_match(m))
    else:
        triples = _prediction_triples(predictions)
    if num_queries is None:
        if sim is not None:
            num_queries = int(sim.shape[0])
        else:
            seen = [q for q, _, _ in triples] + [gt.max_query_index or 0]
            num_queries = max(seen) + 1
    d = _native.evaluate(triples, gt, int(num_queries), int(tolerance), _inputs.exclusions(exclude),
                         sim, [int(n) for n in ns])
    return Evaluation(d["ap"], d["auc"], d["recall_at_100p"], d["recall_at_99p"], d["max_f1"],
                      d["precision_at_full"], d["positives"], d["predicted"], d["correct"],
                      dict(d.get("recall_at_n", [])), d["curve"])


def recall_at_n(S: Any, ground_truth: Any, ns: Sequence[int] = STANDARD_NS, *, tolerance: int = 0,
                exclude: Any = None) -> Dict[int, float]:
    """Recall@N of a similarity matrix `S` (Q x D, queries as rows): the fraction of queries
    with a true match whose N most similar references include one (VPR-methods-evaluation's
    recall@N, VPR_Tutorial's recallAtK), {N: recall}."""
    return evaluate(S, ground_truth, tolerance, exclude=exclude, ns=ns).recall_at_n


@dataclass(frozen=True)
class Estimate:
    """A trip's answer for one frame: `ref` (None when not on the map), the confidence, the
    calibrated `p_correct` and the frame's `status` (`localized`, `uncertain`, `off_map`,
    `lost`)."""

    frame: int
    ref: Optional[int]
    confidence: float
    p_correct: float
    status: str


class Trip:
    """Online localization of a vehicle on one map, as the service's trips: `push` a batch of
    frames (descriptors, or images with `describe`) as it drives and get their estimates. The
    map is `reference_descriptors` (one row per map image, in route order); `describe` turns
    pushed images into descriptors (e.g. `lambda f: seasonloc.hog(f, cell_size=8)`)."""

    def __init__(self, reference_descriptors: Any, *, describe: Optional[Callable[[Any], Any]] = None,
                 fan_out: int = 4, hidden_cost: Union[str, float] = "auto", horizontal: bool = True,
                 lag: int = 32, relocalization: Optional[float] = 1.0, normalize: bool = True,
                 tolerance: int = 1, threshold: float = 0.9) -> None:
        refs = _inputs.matrix(reference_descriptors, "reference descriptors")
        self._describe = describe
        self._trip = _native._Trip(refs, int(fan_out), _hidden_cost(hidden_cost), bool(horizontal), int(lag),
                                   None if relocalization is None else float(relocalization), bool(normalize),
                                   int(tolerance), float(threshold))
        #: The trip's status after the last push: `localized`, `lost` or `relocalized`.
        self.status: Optional[str] = None

    def push(self, frames: Any) -> List[Estimate]:
        """Pushes a batch: a descriptor matrix (one row per frame), or images when the trip has
        a `describe` function. Returns one estimate per new frame; `status` is updated."""
        a = frames if isinstance(frames, np.ndarray) and frames.ndim == 2 and frames.dtype.kind == "f" else None
        if a is None:
            if self._describe is None:
                raise TypeError("push: expected a descriptor matrix (frames x dim); pass `describe=` to push images")
            a = self._describe(frames)
        rows, self.status = self._trip.push(_inputs.matrix(a, "query descriptors"))
        return [Estimate(f, r, c, p, s) for f, r, c, p, s in rows]

    @property
    def frames(self) -> int:
        """Frames pushed so far."""
        return int(self._trip.frames)
