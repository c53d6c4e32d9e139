"""Tests of prtlab/scene/_result.py: ShadeResult's .npz round trip."""

import numpy as np
import pytest

from prtlab.scene import ShadeResult


def test_save_and_load_npz_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    res = ShadeResult()
    for name, n in (("floor", 4), ("a/b", 1), ("empty", 0)):
        res.direct[name], res.indirect[name] = rng.random((n, 3)), rng.random((n, 3))
        res.total[name] = res.direct[name] + res.indirect[name]
    res.stderr = {"total": {"floor": rng.random((4, 3))}}
    res.info = {"method": "reference"}
    path = res.save_npz(tmp_path / "sub" / "radiance.npz")
    back = ShadeResult.load_npz(path)
    for part in ("direct", "indirect", "total"):
        got, want = getattr(back, part), getattr(res, part)
        assert got.keys() == want.keys()
        for name in want:
            np.testing.assert_array_equal(got[name], want[name])
    assert back.stderr.keys() == {"total"} and back.stderr["total"].keys() == {"floor"}
    np.testing.assert_array_equal(back.stderr["total"]["floor"], res.stderr["total"]["floor"])
    assert back.info == {}  # info is not stored


def test_load_npz_reads_no_pickles(tmp_path):
    path = tmp_path / "bad.npz"
    np.savez(path, **{"floor/total": np.array([{"a": 1}], dtype=object)})
    with pytest.raises(ValueError, match="allow_pickle"):
        ShadeResult.load_npz(path)
