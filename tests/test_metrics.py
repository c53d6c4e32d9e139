"""prtlab.compare: the error numbers against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from prtlab.metrics import budget, compare
from prtlab.scene import ShadeResult


def _result(values, stderr=None):
    res = ShadeResult()
    for name, v in values.items():
        v = np.asarray(v, dtype=float)
        res.direct[name], res.indirect[name], res.total[name] = v, 0.5 * v, 1.5 * v
        if stderr is not None:
            for part in ("direct", "indirect", "total"):
                res.stderr.setdefault(part, {})[name] = np.full_like(v, stderr[name])
    return res


def test_a_uniform_scale_error_is_the_scale_and_the_mean_ratio():
    ref = _result({"a": np.ones((10, 3))})
    ours = _result({"a": 1.1 * np.ones((10, 3))})
    row = compare(ours, ref).row("a", "total")
    assert row.rel_rms == pytest.approx(0.1)
    assert row.mean_ratio == pytest.approx(1.1)
    assert row.noise == 0.0 and row.error == pytest.approx(0.1)


def test_noise_is_removed_in_quadrature_and_budgets_are_hypot():
    ref = _result({"a": np.full((4, 3), 2.0)}, stderr={"a": 0.2})   # noise 0.1
    ours = _result({"a": np.full((4, 3), 2.5)})                     # rel_rms 0.25
    row = compare(ours, ref).row("a", "direct")
    assert row.noise == pytest.approx(0.1)
    assert row.error == pytest.approx(math.sqrt(0.25**2 - 0.1**2))
    assert budget(0.2, 0.1) == pytest.approx(math.sqrt(0.05))
    assert not row.meets(0.2)           # 0.25 > hypot(0.2, 0.1) = 0.2236; linearly it would pass (0.3)
    assert row.meets(0.23)


def test_every_object_and_part_is_scored_and_failures_are_named():
    ref = _result({"a": np.ones((3, 3)), "b": np.ones((5, 3))})
    ours = _result({"a": np.ones((3, 3)), "b": 2 * np.ones((5, 3))})
    cmp = compare(ours, ref)
    assert [(r.object, r.part) for r in cmp.rows] == [(o, p) for o in "ab" for p in ("direct", "indirect", "total")]
    failures = cmp.check(0.05)
    assert len(failures) == 3 and all(f.startswith("b ") for f in failures)
    assert "a" in cmp.table() and "mean ratio" in cmp.table()


def test_a_reference_too_noisy_for_the_goal_is_refused():
    ref = _result({"a": np.ones((3, 3))}, stderr={"a": 0.1})
    with pytest.raises(ValueError, match="sample the reference more"):
        compare(ref, ref).check(0.15)


def test_masks_score_only_the_chosen_vertices():
    ref = _result({"a": np.ones((4, 3))})
    ours = _result({"a": np.array([[1.0] * 3, [1.0] * 3, [9.0] * 3, [9.0] * 3])})
    row = compare(ours, ref, masks={"a": np.array([True, True, False, False])}).row("a", "total")
    assert row.rel_rms == 0.0 and row.n_vertices == 2


def test_bad_inputs_are_refused():
    ref = _result({"a": np.ones((3, 3))})
    with pytest.raises(KeyError, match="the result has no"):
        compare(ShadeResult(), ref)
    with pytest.raises(ValueError, match="parts must be among"):
        compare(ref, ref, parts=["all"])
    with pytest.raises(ValueError, match="shape"):
        compare(_result({"a": np.ones((2, 3))}), ref)
    with pytest.raises(ValueError, match="non-finite"):
        compare(_result({"a": np.full((3, 3), np.nan)}), ref)


def test_json_round_trip(tmp_path):
    import json

    ref = _result({"a": np.ones((3, 3)), "dark": np.zeros((2, 3))})
    compare(ref, ref).to_json(tmp_path / "c.json")
    rows = json.loads((tmp_path / "c.json").read_text())["rows"]
    assert rows[0]["rel_rms"] == 0.0 and rows[-1]["rel_rms"] is None
