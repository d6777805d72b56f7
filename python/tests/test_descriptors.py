"""HOG (from folders, paths and pixel arrays), the CNN, and the whole flow against
`seasonloc eval` on generated routes and, when present, on Nordland and Gardens Point."""

import numpy as np
import pytest

import seasonloc as sl


def test_hog_from_folder_paths_and_arrays_agree(route):
    folder = sl.hog(route["reference"], cell_size=8)
    paths = sl.hog(sorted(str(p) for p in route["reference"].iterdir()), cell_size=8)
    arrays = sl.hog(list(route["ref_pixels"]), cell_size=8)
    stacked = sl.hog(route["ref_pixels"], cell_size=8)
    assert folder.shape[0] == 40 and folder.dtype == np.float32
    for other in (paths, arrays, stacked):
        assert np.array_equal(folder, other)
    gray = sl.hog(route["ref_pixels"][..., 0], cell_size=8)  # N x H x W
    assert gray.shape == folder.shape
    half = sl.hog(route["reference"], cell_size=8, resize=(32, 16))
    assert half.shape[1] < folder.shape[1]


def _cli_eval(cli, ref, qry, gt, *extra):
    return cli("eval", "--reference", ref, "--query", qry, "--ground-truth", gt, *extra)


def _flow_equals_cli(cli, ref_dir, qry_dir, gt, cell, tolerance, exclude=None, resize=None):
    ref = sl.hog(ref_dir, cell_size=cell)
    qry = sl.hog(qry_dir, cell_size=cell, resize=resize)
    res = sl.localize(ref, qry, claim=tolerance, tolerance=tolerance)
    ev = sl.evaluate(res, str(gt), tolerance=tolerance, exclude=exclude)
    extra = ["--cell-size", cell, "--tolerance", tolerance] + (["--exclude", exclude] if exclude else [])
    want = _cli_eval(cli, ref_dir, qry_dir, gt, *extra)
    for key in ("ap", "auc", "recall_at_100p", "recall_at_99p", "max_f1", "precision_at_full"):
        assert getattr(ev, key) == want[key], key
    assert (ev.positives, ev.predicted, ev.correct) == (want["positives"], want["predicted"], want["correct"])
    assert {str(n): r for n, r in ev.recall_at_n.items()} == want["recall_at_n"]
    return ev, res


def test_flow_equals_cli_eval_on_a_generated_route(cli, route):
    ev, res = _flow_equals_cli(cli, route["reference"], route["query"], route["gt"], 8, 1)
    assert ev.ap > 0.8
    bm = sl.evaluate(sl.best_match(sl.similarity(sl.hog(route["reference"], cell_size=8),
                                                 sl.hog(route["query"], cell_size=8), normalize=False)),
                     route["gt"], tolerance=1, num_queries=30)
    want = _cli_eval(cli, route["reference"], route["query"], route["gt"], "--cell-size", 8, "--tolerance", 1,
                     "--method", "best-match")
    assert bm.ap == want["ap"]


def test_nordland_equals_cli_eval(cli, nordland):
    ev, res = _flow_equals_cli(cli, nordland / "summer", nordland / "winter", nordland / "ground_truth.csv",
                               8, 1, exclude="0-16")
    assert ev.ap > 0.8, ev  # README: AP 0.863
    S = sl.similarity(sl.hog(nordland / "summer", cell_size=8), sl.hog(nordland / "winter", cell_size=8),
                      normalize=False)
    seq = sl.evaluate(sl.seqslam(S), nordland / "ground_truth.csv", tolerance=1, exclude="0-16", num_queries=2400)
    want = _cli_eval(cli, nordland / "summer", nordland / "winter", nordland / "ground_truth.csv",
                     "--cell-size", 8, "--tolerance", 1, "--exclude", "0-16", "--method", "seqslam")
    assert seq.ap == want["ap"]


def test_gardens_point_equals_cli_eval(cli, gardens_point):
    # The night frames (640x360) are brought to the map's 960x540, as `eval` does.
    _flow_equals_cli(cli, gardens_point / "day_right", gardens_point / "night_right",
                     gardens_point / "gt_night_right_vs_day_right.csv", 32, 2, resize=(960, 540))


def test_cnn_needs_a_model_and_says_so(route):
    if not getattr(sl._native, "HAS_CNN", False):
        with pytest.raises(RuntimeError, match="cnn"):
            sl.cnn(route["reference"], model="m.onnx")
        return
    with pytest.raises((OSError, ValueError), match="missing.onnx"):
        sl.cnn(route["reference"], model=str(route["root"] / "missing.onnx"))


def test_cooc_equals_cli_eval_on_a_generated_route(cli, route):
    for method in ("cooc", "cooc-seq", "cooc-flow"):
        preds = sl.cooc(route["reference"], route["query"], method)
        ev = sl.evaluate(preds, route["gt"], tolerance=0, num_queries=30)
        want = _cli_eval(cli, route["reference"], route["query"], route["gt"], "--method", method)
        assert (ev.ap, ev.predicted, ev.correct) == (want["ap"], want["predicted"], want["correct"]), method
    from_arrays = sl.cooc(list(route["ref_pixels"]), list(route["query_pixels"]))
    assert from_arrays == sl.cooc(route["reference"], route["query"])
    with pytest.raises(ValueError, match="unknown co-occurrence method"):
        sl.cooc(route["reference"], route["query"], "nope")
