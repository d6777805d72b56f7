"""Recall@N and the AUC against hand computations and against VPR_Tutorial's own formulas
(re-implemented below from the definitions in its evaluation/metrics.py) on fixed matrices."""

import numpy as np
import pytest

import seasonloc as sl

D = 24
RANKS = [[0], [0], [0], [0], [0], [1], [2], [3], [4], [4, 19], [5], [6], [7], [9], [9, 12], [10], [12], [15],
         [20], [23], [11, 2], [0, 7], [14, 5], [18]]


def rotated():
    """Query i ranks reference (i + r) % D at rank r: every column a permutation of the same
    values, so the column normalisation cannot reorder a row."""
    v = np.array([1.0 - 0.031 * k for k in range(D)], np.float32)
    return np.array([[v[(j - i) % D] for j in range(D)] for i in range(D)], np.float32)


def gt_pairs():
    return [(q, (q + r) % D) for q, rs in enumerate(RANKS) for r in rs]


def gthard():
    G = np.zeros((D, D), bool)  # references x queries
    for q, r in gt_pairs():
        G[r, q] = True
    return G


def vpr_tutorial_recall_at_k(S, G, K):
    """Recall@K as VPR_Tutorial defines it (evaluation/metrics.py, `recallAtK`), written here
    from that definition: S and G are references x queries; queries without a true reference
    are left out; a query counts when one of its K most similar references is true."""
    hits = counted = 0
    for q in range(S.shape[1]):
        truth = np.asarray(G[:, q], bool)
        if not truth.any():
            continue
        counted += 1
        top = np.argsort(S[:, q], kind="stable")[::-1][:K]
        hits += bool(truth[top].any())
    return hits / counted


def vpr_tutorial_auc_single(S, G, n_thresh=100):
    """The AUC as VPR_Tutorial computes it (`createPR(matching='single')`, then the trapezoid
    rule over recall), written here from that definition: each query keeps its best reference;
    100 thresholds from the highest best score to the lowest; the curve starts at (R 0, P 1)."""
    G = np.asarray(G, bool)
    positives = int(G.any(axis=0).sum())
    best = S.argmax(axis=0)
    right = np.array([G[best[q], q] for q in range(S.shape[1])])
    score = S.max(axis=0)
    recall, precision = [0.0], [1.0]
    for t in np.linspace(score.max(), score.min(), n_thresh):
        kept = score >= t
        tp = int((right & kept).sum())
        fp = int((~right & kept).sum())
        precision.append(tp / (tp + fp))
        recall.append(tp / positives)
    area = 0.0
    for k in range(1, len(recall)):
        area += (recall[k] - recall[k - 1]) * (precision[k] + precision[k - 1]) / 2
    return area


def test_recall_at_n_by_hand_and_by_vpr_tutorial(tmp_path):
    S = rotated()
    hand = {n: sum(1 for rs in RANKS if min(rs) < n) / D for n in (1, 5, 10, 20)}
    assert hand[1] == 6 / 24 and hand[5] == 12 / 24  # q0-4 and q21 at rank 0; ranks 1-4 add q5-9, q20
    tut = {n: vpr_tutorial_recall_at_k(S.T, gthard(), n) for n in (1, 5, 10, 20)}
    assert tut == pytest.approx(hand, abs=1e-12)
    csv = tmp_path / "gt.csv"
    csv.write_text("query_index,ref_index\n" + "".join(f"{q},{r}\n" for q, r in gt_pairs()))
    for gt in (str(csv), gthard(), gt_pairs()):
        ev = sl.evaluate(S, gt, tolerance=0)
        assert ev.recall_at_n == pytest.approx(hand, abs=1e-12)
        assert ev.to_dict()["recall@5"] == pytest.approx(hand[5])
    # From a solution: its similarity matrix is ranked.
    assert sl.evaluate(sl.solve(S), gthard(), tolerance=0).recall_at_n == pytest.approx(hand)
    assert sl.recall_at_n(S, gthard(), ns=(1, 10)) == pytest.approx({1: hand[1], 10: hand[10]})
    # A query without a true match is not counted (VPR_Tutorial discards it).
    fewer = [(q, r) for q, r in gt_pairs() if q != 0]
    assert sl.recall_at_n(S, fewer, ns=(1,))[1] == pytest.approx(5 / 23)


def test_auc_is_vpr_tutorials():
    rng = np.random.default_rng(3)
    for trial in range(5):
        S = rng.random((60, 50)).astype(np.float32) + 0.01  # queries x references, all > 0
        for q in range(60):
            if rng.random() < 0.7:
                S[q, q % 50] += rng.random()
        G = np.zeros((50, 60), bool)
        for q in range(60):
            G[q % 50, q] = True
            if q % 7 == 0:
                G[(q + 3) % 50, q] = True
        want = vpr_tutorial_auc_single(S.T.astype(np.float64), G)
        got = sl.evaluate(S, G, tolerance=0).auc
        assert got == pytest.approx(want, abs=1e-9), trial


def test_pr_metrics_by_hand():
    # 4 queries with a match; ranked: right (0.9), wrong (0.8), right (0.7).
    preds = [sl.Prediction(0, 0, 0.9), sl.Prediction(1, 5, 0.8), {"query": 2, "ref": 2, "confidence": 0.7}]
    ev = sl.evaluate(preds, {0: [0], 1: [1], 2: [2], 3: [3]}, tolerance=0, num_queries=4)
    assert ev.ap == pytest.approx(0.25 + 0.25 * 2 / 3)
    assert ev.recall_at_100p == pytest.approx(0.25)
    assert ev.auc == pytest.approx(0.25 + 0.25 * (0.5 + 2 / 3) / 2)
    assert (ev.positives, ev.predicted, ev.correct) == (4, 3, 2)
    assert ev.recall_at_n == {}  # no similarity matrix: no ranking to score
    ex = sl.evaluate(preds, {0: [0], 1: [1], 2: [2], 3: [3]}, tolerance=0, num_queries=4, exclude="1")
    assert ex.positives == 3 and ex.predicted == 2
    for form in ([1], range(1, 2), [(1, 1)]):
        assert sl.evaluate(preds, {0: [0], 1: [1], 2: [2], 3: [3]}, num_queries=4, exclude=form) == ex
    with pytest.raises(ValueError, match="exclude"):
        sl.evaluate(preds, {0: [0]}, num_queries=4, exclude="5-2")
    with pytest.raises(ValueError, match="two predictions for query 0"):
        sl.evaluate([(0, 0, 1.0), (0, 1, 0.5)], {0: [0]}, num_queries=4)
