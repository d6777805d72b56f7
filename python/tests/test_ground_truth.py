"""Every ground-truth form gives the same scores as the equivalent CSV: VPR-Bench's
`ground_truth_new.npy`, VPR_Tutorial's GThard / GTsoft (`.npz`, `.npy`, array),
VPR-methods-evaluation's UTM folder layout, dicts and pairs; and `seasonloc eval` reads them."""

import numpy as np
import pytest

import seasonloc as sl
from conftest import planted, write_png

Q = 300


def multi():
    """Several true references for some queries; none for a few."""
    gt = {}
    for q in range(Q):
        if q % 50 == 49:
            continue
        refs = [q]
        if q % 7 == 3 and q + 2 < Q:
            refs.append(q + 2)
        if q % 11 == 5 and q >= 3:
            refs.append(q - 3)
        gt[q] = refs
    return gt


@pytest.fixture(scope="module")
def forms(tmp_path_factory):
    d = tmp_path_factory.mktemp("gt")
    gt = multi()
    csv = d / "gt.csv"
    csv.write_text("query_index,query_file,ref_index,ref_file\n" +
                   "".join(f"{q},w/{q},{r},s/{r}\n" for q, refs in gt.items() for r in refs))
    vb = np.empty((len(gt), 2), dtype=object)
    for k, (q, refs) in enumerate(gt.items()):
        vb[k, 0], vb[k, 1] = q, list(refs)
    np.save(d / "ground_truth_new.npy", vb, allow_pickle=True)
    G = np.zeros((Q, Q), bool)
    for q, refs in gt.items():
        G[refs, q] = True
    np.savez(d / "GT.npz", GThard=G, GTsoft=G)
    np.save(d / "GThard.npy", G)
    return {"csv": csv, "vb_path": d / "ground_truth_new.npy", "vb": vb, "npz": d / "GT.npz",
            "gthard_npy": d / "GThard.npy", "G": G, "dict": gt,
            "pairs": [(q, r) for q, refs in gt.items() for r in refs]}


def test_every_form_scores_as_the_csv(forms):
    S = planted(Q, Q, 7, off=(100, 130))
    res = sl.solve(S)
    want = sl.evaluate(res, str(forms["csv"]), tolerance=0)
    assert want.recall_at_n and want.positives == len(forms["dict"])
    for name in ("vb_path", "vb", "npz", "gthard_npy", "G", "dict", "pairs"):
        got = sl.evaluate(res, forms[name], tolerance=0)
        assert got == want, name
        assert sl.evaluate(res, forms[name], tolerance=1) == sl.evaluate(res, forms["csv"], tolerance=1), name
    assert sl.evaluate(res, sl.load_ground_truth(forms["npz"], soft=True)) == want
    gt = sl.load_ground_truth(forms["vb_path"])
    assert gt.references(3) == [3, 5] and len(gt) == len(forms["dict"])


def test_bad_ground_truth_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="no true entry"):
        sl.load_ground_truth(np.zeros((3, 3), bool))
    np.savez(tmp_path / "x.npz", other=np.ones((2, 2), bool))
    with pytest.raises(ValueError, match="no `GThard` array"):
        sl.load_ground_truth(tmp_path / "x.npz")
    (tmp_path / "bad.csv").write_text("query_index,ref\n0,1\n")
    with pytest.raises(ValueError, match="ref_index"):
        sl.load_ground_truth(tmp_path / "bad.csv")
    with pytest.raises(OSError):
        sl.load_ground_truth(tmp_path / "missing.csv")


def test_vpr_methods_evaluation_folder_layout(tmp_path):
    """database/ and queries/ with UTM coordinates in the file names, true within 25 m."""
    root = tmp_path / "dataset" / "test"
    (root / "database").mkdir(parents=True)
    (root / "queries").mkdir()
    img = np.zeros((8, 8), np.uint8)
    for i in range(10):
        write_png(root / "database" / f"@{500000 + 10 * i:.2f}@{4000000:.2f}@33@T@0@0@@@@@@@.png", img)
    for i in range(4):  # 12 m east of database i * 2: within 25 m of db 2i (12 m) and 2i+1 (2 m)
        write_png(root / "queries" / f"@{500012 + 20 * i:.2f}@{4000000:.2f}@33@T@0@0@@@@@@@.png", img)
    gt = sl.load_ground_truth(root)
    assert [gt.references(q) for q in range(4)] == [[0, 1, 2, 3], [1, 2, 3, 4, 5], [3, 4, 5, 6, 7], [5, 6, 7, 8, 9]]
    tight = sl.load_ground_truth(root, distance=5.0)
    assert [tight.references(q) for q in range(4)] == [[1], [3], [5], [7]]
    (root / "queries" / "plain.png").write_bytes((root / "database").joinpath(
        sorted(p.name for p in (root / "database").iterdir())[0]).read_bytes())
    with pytest.raises(ValueError, match="plain.png.*UTM"):
        sl.load_ground_truth(root)
