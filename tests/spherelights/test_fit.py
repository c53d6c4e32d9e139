"""Tests of prtlab.spherelights._fit (variational bounding sphere sets)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prtlab.geometry import builtin_mesh
from prtlab.spherelights import fit_spheres, sphere_set_coverage


@pytest.fixture(scope="module")
def capsule_like():
    # an elongated closed mesh: a box 3 x 1 x 1, subdivided so spheres can take small segments
    return builtin_mesh("box", size=[3.0, 1.0, 1.0], subdivisions=3)


def test_one_sphere_fits_a_sphere_mesh():
    mesh = builtin_mesh("icosphere", subdivisions=2)
    fit = fit_spheres(mesh, 1, grid_resolution=24)
    np.testing.assert_allclose(fit.centres[0], 0.0, atol=0.02)
    # the bounding sphere of an icosphere inscribed in the unit sphere is the unit sphere
    assert abs(fit.radii[0] - 1.0) < 0.02
    assert fit.coverage == 1.0


def test_outside_volume_is_exact_where_the_grid_is():
    """A 2 x 2 x 2 box on a 24-cell grid: the cell midpoints count the box's volume exactly (8), so the
    outside volume of one sphere is the closed form ``4/3 pi R^3 - 8`` with ``R = sqrt(3)`` at the centre."""
    box = builtin_mesh("box", size=[2.0, 2.0, 2.0], subdivisions=2)
    fit = fit_spheres(box, 1, grid_resolution=24)
    np.testing.assert_allclose(fit.centres[0], 0.0, atol=1e-3)
    np.testing.assert_allclose(fit.radii[0], np.sqrt(3.0), rtol=1e-3)
    assert fit.outside_volume == pytest.approx(4.0 / 3.0 * np.pi * fit.radii[0] ** 3 - 8.0, rel=1e-12)
    assert fit.outside_volume == pytest.approx(4.0 / 3.0 * np.pi * 3.0**1.5 - 8.0, rel=1e-2)


def test_coverage_is_exact_on_surface_samples(capsule_like, rng):
    fit = fit_spheres(capsule_like, 4, grid_resolution=24, max_iter=5)
    assert fit.coverage == 1.0
    pts = capsule_like.sample(5000, seed=3)
    assert sphere_set_coverage(pts, fit.centres, fit.radii) == 1.0
    # every vertex of every face lies in the face's sphere (convexity => the face is covered)
    v = capsule_like.vertices[capsule_like.faces]
    d = np.linalg.norm(v - fit.centres[fit.face_sphere][:, None, :], axis=2)
    assert np.all(d <= fit.radii[fit.face_sphere][:, None] * (1 + 1e-9))


def test_outside_volume_decreases_with_n(capsule_like):
    vols = [fit_spheres(capsule_like, n, grid_resolution=24, max_iter=6).outside_volume for n in (1, 3, 8)]
    assert vols[0] > vols[1] > vols[2]


def test_unpacks_and_shapes(capsule_like):
    centres, radii = fit_spheres(capsule_like, 2, grid_resolution=16, max_iter=2)
    assert centres.shape == (2, 3) and radii.shape == (2,)
    assert np.all(radii > 0)


def test_errors(capsule_like):
    with pytest.raises(ValueError, match="n must be an int >= 1"):
        fit_spheres(capsule_like, 0)
    with pytest.raises(ValueError, match="exceeds the number of faces"):
        fit_spheres(capsule_like, 10**6)
    with pytest.raises(TypeError, match="mesh must be a trimesh.Trimesh"):
        fit_spheres("bunny", 2)
    with pytest.raises(ValueError, match="max_iter must be an int >= 1"):
        fit_spheres(capsule_like, 2, max_iter=0)
    with pytest.raises(ValueError, match="grid_resolution must be an int >= 4"):
        fit_spheres(capsule_like, 2, grid_resolution=2)
    with pytest.raises(ValueError, match="mesh has no faces"):
        fit_spheres((np.zeros((3, 3)), np.zeros((0, 3), dtype=int)), 1)
    with pytest.raises(ValueError, match="NaN or inf"):
        fit_spheres((np.full((3, 3), np.nan), np.array([[0, 1, 2]])), 1)


# ------------------------------------------------------------------ tiers of the outside-volume objective


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), n_verts=st.integers(1, 20), n_interior=st.integers(0, 300))
def test_outside_volume_kernel_is_the_reference(seed, n_verts, n_interior):
    from prtlab.spherelights._fit import _outside_volume_kernel, _outside_volume_one

    g = np.random.default_rng(seed)
    c = g.normal(size=3)
    verts = g.normal(size=(n_verts, 3))
    interior = g.normal(size=(n_interior, 3)) * 1.5
    cell = float(g.uniform(1e-4, 1e-2))
    fast = _outside_volume_kernel(c, verts, interior, cell)
    ref = _outside_volume_one(c, verts, interior, cell)
    assert fast == pytest.approx(ref, rel=1e-13, abs=1e-15)


def test_fit_tiers_agree(capsule_like):
    """Same float64 operations in the same order: the Nelder-Mead paths, hence the fits, coincide."""
    fast = fit_spheres(capsule_like, 3, grid_resolution=16, max_iter=3, n_coverage_samples=500)
    ref = fit_spheres(capsule_like, 3, grid_resolution=16, max_iter=3, n_coverage_samples=500, method="reference")
    np.testing.assert_allclose(fast.centres, ref.centres, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.radii, ref.radii, rtol=1e-12)
    np.testing.assert_array_equal(fast.face_sphere, ref.face_sphere)
    assert fast.outside_volume == pytest.approx(ref.outside_volume, rel=1e-12)
    with pytest.raises(ValueError, match="method must be 'numba' or 'reference'"):
        fit_spheres(capsule_like, 2, method="fast")
