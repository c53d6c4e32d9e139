"""The Eq. 13 kernel (``eq13_kernel``) against the float64 tier.

The kernel blends the 8 corners' rows term by term and dots the blend with the transfer, in any order (fastmath
``reassoc``, ``contract``): a value of ``8 n2`` terms has at most ``n2 + 13`` roundings on any term's path, so it
differs from the exact sum by at most ``(n2 + 14) 2^-53`` of the sum of its terms' magnitudes, and the float64 tier
(``method="reference"``) by at most twice that. Taking the vertices in cell order (``in_cell_order``, for fields
larger than the caches) changes nothing: each vertex's arithmetic is the same, bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import prtlab.interreflection._passes as passes
from prtlab.geometry import builtin_mesh
from prtlab.interreflection import basis_irradiance
from prtlab.interreflection._fields import store_basis_radiance
from prtlab.interreflection._kernels import eq13_kernel
from prtlab.shadowfields import sphere_grid

GRID = sphere_grid(builtin_mesh("icosphere", subdivisions=1), n_radii=4, resolution=3)


def _bound(n2: int) -> float:
    """Twice the kernels' relative bound: both tiers err by at most ``(n2 + 14) 2^-53`` of the |terms|."""
    return 2 * (n2 + 14) * 2.0**-53


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), storage=st.sampled_from([None, "float64", "float32", "int16"]),
       order=st.sampled_from([1, 2, 3, 4]), n_kp=st.integers(1, 3))
def test_kernels_within_the_arithmetic_bound_of_the_float64_tier_in_either_vertex_order(seed, storage, order, n_kp):
    rng = np.random.default_rng(seed)
    n2 = order * order
    field = rng.normal(size=GRID.shape + (2, 3, n2)) * 10.0 ** rng.uniform(-3, 1, GRID.shape + (2, 3, 1))
    field[rng.random(GRID.shape) < 0.3] = 0.0
    source = field if storage is None else store_basis_radiance(field, storage)
    dense = field if storage is None else source.dense()
    points = GRID.center + rng.normal(size=(40, 3)) * GRID.radii[-1] * 0.7  # some beyond the outermost sphere
    transfer = rng.normal(size=(40, n_kp, n2))
    fast = basis_irradiance(source, GRID, points, transfer)
    ref = basis_irradiance(dense, GRID, points, transfer, method="reference")
    terms = basis_irradiance(np.abs(dense), GRID, points, np.abs(transfer), method="reference")
    assert np.all(np.abs(fast - ref) <= _bound(n2) * terms + 1e-300)
    # the same values, bit for bit, with the vertices taken in cell order
    a, b = (_kernel(source, points, transfer, in_cell_order) for in_cell_order in (False, True))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a.reshape(fast.shape), fast)


def _kernel(source, points, transfer, in_cell_order):
    """``eq13_kernel`` on a dense field or a stored one at the identity pose, vertices in either order."""
    n_s = int(np.prod(GRID.shape))
    if isinstance(source, np.ndarray):
        m = source.shape[4] * source.shape[5]
        args = (np.arange(n_s, dtype=np.int32), np.ascontiguousarray(source.reshape(n_s, m, -1)),
                np.empty((0, m), np.float32), False)
    else:
        m = source.values.shape[1]
        args = (source.rows.reshape(-1), source.values, source.scale, source.storage == "int16")
    out = np.empty((len(points), transfer.shape[1], m))
    assert eq13_kernel(*args, points, np.zeros(3), np.eye(3), 1.0, GRID.center, GRID.radii, GRID.shape[2],
                       np.empty((0, 0)), transfer, in_cell_order, out)
    return out


def test_large_fields_are_read_in_cell_order_with_the_same_values(monkeypatch, rng):
    field = rng.normal(size=GRID.shape + (1, 2, 4))
    points = rng.normal(size=(50, 3)) * GRID.radii[-1] * 0.5
    transfer = rng.normal(size=(50, 2, 4))
    stored = store_basis_radiance(field, "int16")
    before = basis_irradiance(field, GRID, points, transfer), basis_irradiance(stored, GRID, points, transfer)
    monkeypatch.setattr(passes, "_CELL_ORDER_BYTES", 0)  # every field "large"
    after = basis_irradiance(field, GRID, points, transfer), basis_irradiance(stored, GRID, points, transfer)
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])


def test_vertices_whose_corners_hold_no_rows_get_zero_and_bad_input_is_refused(rng):
    """A stored field that is 0 on the inner spheres keeps no rows there: vertices whose 8 corners all lie there get
    exactly 0 (the kernel reads no row), those beside it the float64 tier's values; a NaN transfer is refused."""
    field = rng.normal(size=GRID.shape + (1, 2, 4))
    field[:2] = 0.0
    stored = store_basis_radiance(field, "float64")
    assert np.all(stored.rows[:2] < 0)
    inner = GRID.center + rng.normal(size=(20, 3)) * 1e-3  # on the first sphere: corners on spheres 0 and 1
    outer = GRID.center + rng.normal(size=(20, 3)) * GRID.radii[-1] * 0.6
    points = np.concatenate([inner, outer])
    transfer = rng.normal(size=(40, 1, 4))
    got = basis_irradiance(stored, GRID, points, transfer)
    assert np.all(got[:20] == 0.0)
    ref = basis_irradiance(field, GRID, points, transfer, method="reference")
    terms = basis_irradiance(np.abs(field), GRID, points, np.abs(transfer), method="reference")
    assert np.all(np.abs(got - ref) <= _bound(4) * terms + 1e-300)
    transfer[3, 0, 2] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        basis_irradiance(stored, GRID, points, transfer)
