"""Tests of prtlab/_validate.py: the shared validators' answers to bad input."""

import numpy as np
import pytest

from prtlab._validate import MemoryNeed, as_points, as_real_array, check_bool, check_choice, check_float, check_memory


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


def test_as_real_array_converts_or_names_the_fault():
    arr = as_real_array(np.array([[1, 2]], np.int32), "x")
    assert arr.dtype == np.float64 and arr.shape == (1, 2)
    assert as_real_array(np.zeros(0), "x").shape == (0,)
    with pytest.raises(TypeError, match="factors must be a real array, got dtype <U1"):
        as_real_array(["a"], "factors")
    with pytest.raises(ValueError, match="^weights contains NaN or inf$"):
        as_real_array([1.0, np.nan], "weights")
    with pytest.raises(ValueError, match="image contains NaN or inf; environment maps must be finite"):
        as_real_array([np.inf], "image", "environment maps must be finite")


def test_check_float_accepts_ints_and_floats_in_range():
    assert check_float(1, "x") == 1.0 and isinstance(check_float(np.float32(0.5), "x", 0, 1), float)
    assert check_float(0.0, "x", 0.0, 1.0, max_open=True) == 0.0


@pytest.mark.parametrize("value, error, message", [
    (True, TypeError, r"x must be a finite number >= 0 and < 1, got True of type bool"),
    ("0.5", TypeError, r"x must be a finite number >= 0 and < 1, got '0.5' of type str"),
    (np.nan, ValueError, r"x must be a finite number >= 0 and < 1, got nan"),
    (np.inf, ValueError, r"got inf"),
    (1.0, ValueError, r"< 1, got 1.0"),
    (-0.5, ValueError, r">= 0 and < 1, got -0.5"),
])
def test_check_float_errors(value, error, message):
    with pytest.raises(error, match=message):
        check_float(value, "x", 0, 1, max_open=True)
    with pytest.raises(ValueError, match=r"y must be a finite number > 0 \(in metres\), got 0"):
        check_float(0, "y", 0, min_open=True, meaning="in metres")


def test_check_bool():
    assert check_bool(np.bool_(True), "flag") is True
    with pytest.raises(TypeError, match="flag must be True or False, got 1 of type int"):
        check_bool(1, "flag")


def test_check_choice_compares_type_and_value():
    assert check_choice("sh", "option shadows", ("sh", "haar")) == "sh"
    assert check_choice(np.str_("sh"), "option shadows", ("sh", "haar")) == "sh"
    with pytest.raises(ValueError, match="option n must be one of 1, 2, got True"):
        check_choice(True, "option n", (1, 2))
    with pytest.raises(ValueError, match=r"option s must be one of 'a', 'b', got array"):
        check_choice(np.array(["a", "b"]), "option s", ("a", "b"))


def test_check_memory_names_the_largest_allocation_first(monkeypatch):
    monkeypatch.setenv("PRTLAB_MAX_MEMORY_GB", "20")
    needs = [MemoryNeed("the transfer", 30 * 2**30, ("order", "bounces")), MemoryNeed("the cubemaps", 2**30, ("res",)),
             MemoryNeed("the grid", 5 * 2**30, ("res",))]
    opts = {"order": 8, "bounces": 40, "res": 64}
    with pytest.raises(ValueError, match=r"^portals: option order=8 with bounces=40 and res=64 needs ~36 GB for 2,191 "
                                         r"vertices \(limit 20 GB; mostly the transfer\): lower order, bounces or res "
                                         r"\(or set PRTLAB_MAX_MEMORY_GB\)$"):
        check_memory("portals", opts, needs, "2,191 vertices")
    check_memory("portals", opts, needs[1:], "2,191 vertices")  # 6 GB fits
    monkeypatch.setenv("PRTLAB_MAX_MEMORY_GB", "0.001")
    with pytest.raises(ValueError, match=r"option res=64 needs ~6 GB for 1 thing \(limit 1.02 MB; mostly the "
                                         r"cubemaps\): lower res \("):
        check_memory("x", opts, needs[1:2] * 6, "1 thing")
