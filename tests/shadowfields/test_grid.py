"""Tests of prtlab/shadowfields/_grid.py: sample spheres and the trilinear lookup."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.geometry import builtin_mesh, direction_to_cubemap
from prtlab.shadowfields import SphereGrid, bounding_sphere, interpolate_field, sphere_grid
from tests.conftest import FLOAT_TOLERANCE, random_directions

MESH = builtin_mesh("icosphere", subdivisions=1)


def test_grid_points_lie_on_their_spheres_in_cubemap_directions():
    grid = sphere_grid(MESH, n_radii=3, resolution=4, r_min=0.5, r_max=2.0)
    pts = grid.points()
    assert pts.shape == (3, 6, 4, 4, 3) == grid.shape + (3,)
    r = np.linalg.norm(pts - grid.center, axis=-1)
    np.testing.assert_allclose(r, np.broadcast_to(grid.radii[:, None, None, None], r.shape))
    np.testing.assert_allclose(grid.radii, grid.radius * np.geomspace(0.5, 2.0, 3))
    face, s, t = direction_to_cubemap(grid.directions())
    np.testing.assert_array_equal(face, np.broadcast_to(np.arange(6)[:, None, None], face.shape))
    uniform = sphere_grid(MESH, n_radii=3, resolution=2, r_min=1.0, r_max=3.0, spacing="uniform")
    np.testing.assert_allclose(uniform.radii / uniform.radius, [1.0, 2.0, 3.0])
    assert sphere_grid(MESH, n_radii=1).radii.shape == (1,)


def test_bounding_sphere_of_a_box():
    c, r = bounding_sphere(np.array([[0.0, 0, 0], [2, 0, 0], [2, 2, 2]]))
    np.testing.assert_allclose(c, [1, 1, 1])
    assert r == pytest.approx(np.sqrt(3))


@pytest.mark.parametrize("method", ["numba", "reference"])
def test_lookup_reproduces_grid_values_and_linear_fields(method, rng):
    grid = sphere_grid(MESH, n_radii=4, resolution=5, spacing="uniform")
    pts = grid.points()
    values = np.stack([np.linalg.norm(pts - grid.center, axis=-1), pts[..., 0] * 0 + 1.0], axis=-1)
    out, beyond = interpolate_field(grid, values, pts, method=method)
    np.testing.assert_allclose(out, values, atol=1e-12)
    assert not beyond.any()
    # a field linear in the radius is reproduced off the grid (uniform spacing: linear in the index too)
    d = random_directions(rng, 50)
    r = rng.uniform(grid.radii[0], grid.radii[-1], 50)
    out, _ = interpolate_field(grid, values, grid.center + r[:, None] * d, method=method)
    np.testing.assert_allclose(out[:, 0], r, rtol=1e-12)
    np.testing.assert_allclose(out[:, 1], 1.0, rtol=1e-12)


@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(0.0, 12.0))
def test_numba_tier_equals_reference_tier(seed, scale):
    rng = np.random.default_rng(seed)
    grid = sphere_grid(MESH, n_radii=3, resolution=3)
    values = rng.normal(size=grid.shape + (2, 3))
    pts = grid.center + scale * grid.radius * random_directions(rng, 20)
    a, ba = interpolate_field(grid, values, pts, method="numba")
    b, bb = interpolate_field(grid, values, pts, method="reference")
    np.testing.assert_allclose(a, b, atol=FLOAT_TOLERANCE[np.float64])
    np.testing.assert_array_equal(ba, bb)
    assert a.shape == (20, 2, 3)


def test_empty_and_batched_queries():
    grid = sphere_grid(MESH, n_radii=2, resolution=2)
    values = np.ones(grid.shape + (4,))
    out, beyond = interpolate_field(grid, values, np.zeros((0, 3)))
    assert out.shape == (0, 4) and beyond.shape == (0,)
    out, beyond = interpolate_field(grid, values, np.zeros((2, 3, 3)))  # the centre itself
    assert out.shape == (2, 3, 4) and np.all(out == 1.0)


def test_beyond_is_reported():
    grid = sphere_grid(MESH, n_radii=2, resolution=2, r_min=1, r_max=2)
    _, beyond = interpolate_field(grid, np.zeros(grid.shape + (1,)), [[0, 0, 2.5 * grid.radius], [0, 0, 0.5]])
    np.testing.assert_array_equal(beyond, [True, False])


def test_round_trip_arrays():
    grid = sphere_grid(MESH, n_radii=2, resolution=3)
    back = SphereGrid.from_arrays(grid.to_arrays())
    np.testing.assert_array_equal(back.radii, grid.radii)
    assert back.resolution == 3 and back.radius == grid.radius


def test_errors():
    grid = sphere_grid(MESH, n_radii=2, resolution=2)
    with pytest.raises(ValueError, match="spacing must be"):
        sphere_grid(MESH, spacing="log")
    with pytest.raises(ValueError, match="0 < r_min <= r_max"):
        sphere_grid(MESH, r_min=2.0, r_max=1.0)
    with pytest.raises(ValueError, match="n_radii must be an int >= 1"):
        sphere_grid(MESH, n_radii=0)
    with pytest.raises(TypeError, match="resolution must be an int"):
        sphere_grid(MESH, resolution=2.5)
    with pytest.raises(ValueError, match="no vertices"):
        bounding_sphere(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="values must be"):
        interpolate_field(grid, np.zeros((3, 6, 2, 2)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="points must be a"):
        interpolate_field(grid, np.zeros(grid.shape), np.zeros((1, 2)))
    with pytest.raises(ValueError, match="NaN or inf"):
        interpolate_field(grid, np.zeros(grid.shape), [[np.nan, 0, 0]])
    with pytest.raises(ValueError, match="method must be"):
        interpolate_field(grid, np.zeros(grid.shape), np.zeros((1, 3)), method="fast")


@pytest.mark.parametrize("spacing", ["geometric", "uniform"])
def test_locate_kernel_is_the_numpy_path_bit_for_bit(spacing):
    """``SphereGrid.locate``'s kernel against its numpy path: random points near and far (inside the innermost
    sphere, beyond the outermost), on the radii exactly, at the centre, on the cube's edges and corners (ties of
    ``|x|``, ``|y|``, ``|z|``, signed zeros); a call with a non-finite point takes the numpy path."""
    grid = sphere_grid(MESH, n_radii=6, resolution=8, spacing=spacing)
    rng = np.random.default_rng(5)
    d = rng.normal(size=(20_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = np.exp(rng.uniform(np.log(0.01), np.log(12.0), size=(20_000, 1)))
    ties = np.array([[1.0, 1.0, 0.0], [1.0, -1.0, 1.0], [-0.0, 0.0, 1.0], [0.0, -0.0, -1.0], [-1.0, -1.0, -1.0],
                     [0.0, 2.0, -2.0], [3.0, 0.0, 0.0], [-0.0, -0.0, 0.0]])
    on_radii = grid.center + grid.radii[:, None] * d[:len(grid.radii)]
    points = np.concatenate([grid.center + r * d, grid.center + ties, on_radii, grid.center[None]])
    got, want = grid.locate(points), grid.locate(points, method="numpy")
    for a, b in zip(got, want):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert want[4].any() and not want[4].all()
    bad = np.array([[np.nan, 0.0, 0.0], [1.0, 0.0, 0.0]])  # non-finite points: numpy's answers, whatever they are
    for a, b in zip(grid.locate(bad), grid.locate(bad, method="numpy")):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="method"):
        grid.locate(points, method="fast")
