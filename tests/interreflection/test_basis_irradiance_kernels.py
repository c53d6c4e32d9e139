"""The Eq. 13 kernels (``basis_irradiance_kernel``, ``stored_basis_irradiance_kernel``) against the float64 tier.

The kernels sum each corner's ``n2`` products in any order (fastmath ``reassoc``, ``contract``): a value of
``8 n2`` terms has at most ``n2 + 14`` roundings on any term's path, so it differs from the exact sum by at most
``(n2 + 14) 2^-53`` of the sum of its terms' magnitudes, and the float64 tier (``method="reference"``) by at most
twice that. Taking the vertices in cell order (``in_cell_order``, for fields larger than the caches) changes
nothing: each vertex's arithmetic is the same, bit for bit.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

import prtlab.interreflection._passes as passes
from prtlab.geometry import builtin_mesh
from prtlab.interreflection import basis_irradiance
from prtlab.interreflection._fields import store_basis_radiance
from prtlab.interreflection._kernels import basis_irradiance_kernel, stored_basis_irradiance_kernel
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
    rpos, face, s, t, _ = GRID.locate(points)
    scale = (GRID.radii[-1] / np.maximum(np.linalg.norm(points - GRID.center, axis=1), GRID.radii[-1])) ** 2
    a, b = np.empty((40, n_kp, 6)), np.empty((40, n_kp, 6))
    if storage is None:
        flat = np.ascontiguousarray(field.reshape(GRID.shape + (6, n2)))
        basis_irradiance_kernel(flat, rpos, face, s, t, transfer, scale, False, a)
        basis_irradiance_kernel(flat, rpos, face, s, t, transfer, scale, True, b)
    else:
        args = (source.rows, source.values, source.scale, storage == "int16", rpos, face, s, t, transfer, scale)
        stored_basis_irradiance_kernel(*args, False, a)
        stored_basis_irradiance_kernel(*args, True, b)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a.reshape(fast.shape), fast)


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
