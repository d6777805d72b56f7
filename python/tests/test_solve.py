"""`solve`, `similarity`, `localize` and the baselines on generated matrices; `solve` equals
`seasonloc solve` on the same matrix exactly."""

import numpy as np
import pytest

import seasonloc as sl
from conftest import planted


def test_solve_equals_the_cli_exactly(cli, tmp_path):
    S = planted(300, 400, 20261201)
    np.save(tmp_path / "S.npy", S)
    for flags, kwargs in (([], {}), (["--flows", "2"], {"flows": 2}), (["--normalize"], {"normalize": True}),
                          (["--hidden-cost", "0.8", "--fan-out", "3"], {"hidden_cost": 0.8, "fan_out": 3})):
        want = cli("solve", "--similarity", tmp_path / "S.npy", *flags)
        got = sl.solve(S, **kwargs).to_dict()
        assert got == want, flags


def test_solve_result_shape_and_fields():
    S = planted(200, 300, 5)
    res = sl.solve(S, fan_out=4)
    assert isinstance(res, sl.Solution) and res.num_queries == 200
    assert res.hypotheses[0].rank == 1 and len(res.hypotheses[0].rows) == 200
    p = res.predictions[0]
    assert {"query", "ref", "confidence", "p_correct"} <= set(vars(p))
    assert all(0.0 <= q.p_correct <= 1.0 for q in res.predictions)
    # Off the route (rows 120-139) there are few predictions; on it most are on the route.
    on = [q for q in res.predictions if not 120 <= q.query < 140]
    assert len(on) > 150
    assert res.similarity is not None and res.similarity.shape == (200, 300)
    assert len(sl.solve(S, flows=2, exact=True).hypotheses) == 2


def test_similarity_is_the_cosine_and_its_normalisation():
    rng = np.random.default_rng(0)
    ref, qry = rng.random((50, 16)), rng.random((40, 16))
    raw = sl.similarity(ref, qry, normalize=False)
    want = (qry / np.linalg.norm(qry, axis=1, keepdims=True)) @ (ref / np.linalg.norm(ref, axis=1, keepdims=True)).T
    assert raw.shape == (40, 50) and raw.dtype == np.float32
    assert np.allclose(raw, want, atol=1e-5)
    eq2 = sl.similarity(ref, qry, normalize="eq2")
    assert np.allclose(eq2, raw / raw.mean(axis=0, keepdims=True), rtol=1e-5)
    assert sl.similarity(ref, qry).shape == (40, 50)  # the floored default


def test_localize_is_similarity_then_solve():
    rng = np.random.default_rng(1)
    ref = rng.random((120, 32)).astype(np.float32)
    qry = ref[10:90] + 0.05 * rng.random((80, 32)).astype(np.float32)
    res = sl.localize(ref, qry)
    chat = sl.similarity(ref, qry, normalize=True)
    direct = sl.solve(chat, fan_out=4)
    assert res.similarity.shape == (80, 120)
    right = sum(abs(p.ref - (p.query + 10)) <= 1 for p in res.predictions)
    assert right >= 70, right
    # localize's confidences use claim = tolerance (as `eval`); with claim 0 the matches equal solve's on ĉ.
    zero = sl.localize(ref, qry, claim=0)
    assert [(p.query, p.ref, p.confidence) for p in zero.predictions] == \
        [(p.query, p.ref, p.confidence) for p in direct.predictions]


def test_baselines():
    S = planted(100, 150, 9, off=(0, 0))
    bm = sl.best_match(S)
    assert [p.ref for p in bm] == list(np.argmax(S, axis=1))
    assert all(abs(p.confidence - S[p.query, p.ref]) < 1e-6 for p in bm)
    seq = sl.seqslam(S)
    assert seq and all(isinstance(p, sl.Prediction) for p in seq)
    with pytest.raises(ValueError, match="ds"):
        sl.seqslam(S, ds=0)
