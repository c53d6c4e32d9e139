"""Tests of prtlab/interreflection/_fields.py: basis radiance of a source object."""

from __future__ import annotations

import numpy as np
import pytest

from prtlab import brdf
from prtlab.geometry import builtin_mesh
from prtlab.interreflection import basis_radiance_at, basis_radiance_field
from prtlab.scene import AreaLight
from prtlab.shadowfields import area_light_sh, sphere_grid

ORDER = 4
PLANE = builtin_mesh("plane", size=[2.0, 2.0], resolution=[4, 4])  # y = 0, normals +y
LAMBERT = brdf.separable(brdf.lambert(np.ones(3)), 1, resolution=(8, 16))


@pytest.mark.parametrize("degree, rms_bound", [(63, 0.07), (127, 0.035)])
def test_constant_basis_on_a_plane_is_the_sh_of_the_plane_seen_as_an_area_light(rng, degree, rms_bound):
    """Psi = 1 on a flat source: S is the indicator of the directions that see its front side, which is
    what area_light_sh integrates over the light's area (an independent route, converged at 24 nodes).
    The ray-cast projection of the step converges like 1 / degree: measured relative rms 0.116, 0.048,
    0.025, 0.012 at degrees 31, 63, 127, 255 (40 points 0.5..2 above the plane)."""
    points = np.stack([rng.uniform(-1.5, 1.5, 20), rng.uniform(0.5, 2.0, 20), rng.uniform(-1.5, 1.5, 20)], axis=1)
    s = basis_radiance_at(PLANE, np.ones((1, len(PLANE.vertices))), LAMBERT, points, ORDER, degree=degree)
    assert s.shape == (20, 1, 1, 16)
    light = AreaLight(center=np.zeros(3), u=np.array([0.0, 0.0, 1.0]), v=np.array([1.0, 0.0, 0.0]),
                      radiance=np.ones(3))  # cross(u, v) = +y: the front side
    ref = area_light_sh(light, points, ORDER, n_nodes=24)[..., 0]
    err = np.linalg.norm(s[:, 0, 0] - ref, axis=1) / np.linalg.norm(ref, axis=1)
    assert np.sqrt(np.mean(err**2)) < rms_bound
    # behind the plane the front side is not seen
    below = basis_radiance_at(PLANE, np.ones((1, len(PLANE.vertices))), LAMBERT, points * [1, -1, 1], ORDER, 31)
    np.testing.assert_array_equal(below, 0.0)


def test_basis_radiance_is_linear_in_the_basis_and_scaled_by_h(rng):
    psi = rng.normal(size=(3, len(PLANE.vertices)))
    p = np.array([[0.2, 1.0, -0.3]])
    s = basis_radiance_at(PLANE, psi, LAMBERT, p, ORDER, degree=31)
    combo = basis_radiance_at(PLANE, (np.array([1.0, -2.0, 0.5]) @ psi)[None], LAMBERT, p, ORDER, degree=31)
    np.testing.assert_allclose(combo[0, 0, 0], np.array([1.0, -2.0, 0.5]) @ s[0, 0], atol=1e-12)
    glossy = brdf.separable(brdf.phong(0.2, 0.6, 10.0), 3, resolution=(16, 32))
    sg = basis_radiance_at(PLANE, psi, glossy, p, ORDER, degree=31)
    assert sg.shape == (1, 3, 3, 16)


def test_field_on_the_grid_and_errors():
    grid = sphere_grid(PLANE, n_radii=2, resolution=2)
    f = basis_radiance_field(PLANE, np.ones((2, len(PLANE.vertices))), LAMBERT, grid, 2, degree=7)
    assert f.shape == grid.shape + (1, 2, 4)
    with pytest.raises(ValueError, match="basis must be"):
        basis_radiance_at(PLANE, np.ones((2, 3)), LAMBERT, np.zeros((1, 3)), 2)
    with pytest.raises(ValueError, match="order must be"):
        basis_radiance_at(PLANE, np.ones((1, 25)), LAMBERT, np.zeros((1, 3)), 0)
    with pytest.raises(ValueError, match="points must be"):
        basis_radiance_at(PLANE, np.ones((1, 25)), LAMBERT, np.zeros(2), 2)
