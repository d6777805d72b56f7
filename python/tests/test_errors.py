"""Bad input: a Python exception with the CLI's message, never a crash; arrays of another
layout or type converted, or refused clearly."""

import numpy as np
import pytest

import seasonloc as sl
from conftest import planted


def test_nan_and_1d_raise_the_clis_message(cli, tmp_path):
    S = planted(20, 30, 3)
    S[4, 5] = np.nan
    with pytest.raises(ValueError) as e:
        sl.solve(S)
    np.save(tmp_path / "nan.npy", S)
    p = cli("solve", "--similarity", tmp_path / "nan.npy", ok=False)
    assert p.returncode != 0
    assert str(e.value) in p.stderr and "row 4, column 5" in str(e.value)
    with pytest.raises(ValueError, match=r"expected a 2-D array \(Q, D\), got shape \[10\]"):
        sl.solve(np.ones(10, np.float32))
    np.save(tmp_path / "one.npy", np.ones(10, np.float32))
    assert "expected a 2-D array (Q, D), got shape [10]" in cli("solve", "--similarity", tmp_path / "one.npy", ok=False).stderr


def test_bad_parameters_give_the_clis_message(cli, tmp_path):
    S = planted(20, 30, 3)
    np.save(tmp_path / "S.npy", S)
    for kwargs, flags in (({"fan_out": 100000}, ["--fan-out", "100000"]), ({"flows": 0}, ["--flows", "0"]),
                          ({"stop_hidden_fraction": 2.0}, ["--stop-hidden-fraction", "2"])):
        with pytest.raises(ValueError) as e:
            sl.solve(S, **kwargs)
        p = cli("solve", "--similarity", tmp_path / "S.npy", *flags, ok=False)
        assert p.returncode != 0 and str(e.value) in p.stderr, (str(e.value), p.stderr)
    with pytest.raises(ValueError, match="hidden_cost"):
        sl.solve(S, hidden_cost=-1)


def test_layouts_and_types_are_converted_or_refused():
    S = planted(40, 60, 4)
    base = sl.solve(S).to_dict()
    wide = np.zeros((40, 120), np.float32)
    wide[:, ::2] = S
    assert sl.solve(wide[:, ::2]).to_dict() == base  # non-contiguous
    assert sl.solve(np.asfortranarray(S)).to_dict() == base  # Fortran order
    assert sl.solve(S.astype(np.float64)).to_dict() == base  # float64, as the CLI reads it
    with pytest.raises(TypeError, match="expected float32 or float64 data, got dtype <U1"):
        sl.solve(np.full((3, 3), "x"))
    with pytest.raises(TypeError):
        sl.solve(np.ones((3, 3), dtype=complex))
    with pytest.raises(ValueError, match="empty"):
        sl.solve(np.ones((0, 3), np.float32))
    with pytest.raises(ValueError, match="non-finite"):
        sl.similarity(np.ones((3, 4)), np.full((2, 4), np.inf))
    with pytest.raises(ValueError, match="shape mismatch"):
        sl.similarity(np.ones((3, 4)), np.ones((2, 5)))
    with pytest.raises(TypeError, match="uint8"):
        sl.hog([np.zeros((32, 64), np.float32)], cell_size=8)
    with pytest.raises((OSError, ValueError), match="missing.png"):
        sl.hog(["/nonexistent/missing.png"], cell_size=8)
    # The process survives all of it.
    assert sl.solve(S).to_dict() == base
