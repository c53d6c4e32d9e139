"""Tests of prtlab/_validate.py: the shared validators' answers to bad input."""

import numpy as np
import pytest

from prtlab._validate import as_points


def test_as_points_keeps_batch_axes_or_asks_for_a_flat_list():
    p = as_points([[[0, 1, 2]]])
    assert p.shape == (1, 1, 3) and p.dtype == np.float64
    flat = as_points(np.zeros((4, 3), np.float32), flat=True)
    assert flat.dtype == np.float64 and flat.flags.c_contiguous
    assert as_points(np.zeros((0, 3)), flat=True).shape == (0, 3)


def test_as_points_errors():
    with pytest.raises(TypeError, match="points must be a real array of points, got dtype"):
        as_points(np.array([["a", "b", "c"]]))
    with pytest.raises(ValueError, match=r"centres must be a \(\.\.\., 3\) array of points, got shape \(2, 2\)"):
        as_points(np.zeros((2, 2)), "centres")
    with pytest.raises(ValueError, match=r"points must be a \(V, 3\) array of points, got shape \(1, 1, 3\)"):
        as_points(np.zeros((1, 1, 3)), flat=True)
    with pytest.raises(ValueError, match="normals contains NaN or inf; pass finite coordinates"):
        as_points([[0.0, np.inf, 0.0]], "normals")
