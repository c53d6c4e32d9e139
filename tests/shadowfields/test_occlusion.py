"""Tests of prtlab/shadowfields/_occlusion.py: occlusion fields and self-visibility.

Error measure: the SH distance between two visibility vectors relative to the
norm of the blocker's own part ``||1 - V||`` (the shadow), so a small blocker
is not hidden behind the constant term.
"""

from __future__ import annotations

import numpy as np
import pytest

from prtlab import sh
from prtlab.geometry import RayCaster, builtin_mesh
from prtlab.scene import Transform
from prtlab.shadowfields import OcclusionField, occlusion_field, project_visibility, self_visibility
from tests.conftest import random_directions

ORDER = 4
ONE = np.zeros(ORDER * ORDER)
ONE[0] = np.sqrt(4.0 * np.pi)
SPHERE = builtin_mesh("icosphere", subdivisions=3)  # inscribed in the unit sphere
QUICK = dict(n_radii=8, resolution=8, degree=31)


@pytest.fixture(scope="module")
def sphere_oof():
    return occlusion_field(SPHERE, ORDER, **QUICK)


def cap_visibility(points, center=np.zeros(3), radius=1.0):
    """Closed form: a sphere blocker seen from outside, ``blocker_zh`` turned toward its centre."""
    d = center - points
    dist = np.linalg.norm(d, axis=-1)
    return sh.zh_rotate(sh.blocker_zh(np.arcsin(radius / dist), ORDER), d / dist[..., None])


def relative_to_shadow(v, ref):
    return np.linalg.norm(v - ref, axis=-1) / np.linalg.norm(ONE - ref, axis=-1)


def off_grid_points(rng, n, lo, hi):
    return random_directions(rng, n) * rng.uniform(lo, hi, (n, 1))


# --------------------------------------------------------------------------- known answers


#: A step function's product-Gauss quadrature converges like 1 / degree: each doubling of the degree
#: halves the error; 0.6 leaves room for where the edge falls among the nodes.
STEP_RATE = 0.6


def test_projected_visibility_of_a_sphere_is_its_cap(rng):
    """The ray-cast projection of a sphere's visibility converges to the closed-form cap at the step
    function's rate (:data:`STEP_RATE` per doubling of the degree, rms and max over points 1.5..4 radii
    away), so its limit is the cap (the tessellation's share is below the degree-127 error)."""
    q = off_grid_points(rng, 200, 1.5, 4.0)
    errors = []
    for degree in (31, 63, 127):
        err = relative_to_shadow(project_visibility(RayCaster([SPHERE]), q, ORDER, degree=degree), cap_visibility(q))
        errors.append((np.sqrt(np.mean(err**2)), err.max()))
    for coarse, fine in zip(errors, errors[1:]):
        assert fine[0] <= STEP_RATE * coarse[0] and fine[1] <= STEP_RATE * coarse[1], errors


def test_occlusion_field_at_grid_points_is_the_direct_projection(sphere_oof):
    pts = sphere_oof.grid.points()[::3, :, ::3, ::3].reshape(-1, 3)
    direct = project_visibility(RayCaster([SPHERE]), pts, ORDER, degree=QUICK["degree"])
    np.testing.assert_allclose(sphere_oof.lookup(pts), direct, atol=1e-12)


def test_interpolation_error_off_grid(sphere_oof, rng):
    """Trilinear interpolation against the direct projection at off-grid points 1.5..6 radii away, with
    the same quadrature (so only the interpolation error remains). Measured on 2 x 3000 points with
    other seeds, quick grid (8 radii, 6 x 8 x 8): rms 0.23-0.25, 95th percentile 0.46-0.49 of the
    shadow's norm; default grid (16 radii, 6 x 16 x 16, slow test below): rms 0.10-0.11, p95 0.18-0.19.
    The maximum is a heavy tail (up to 1.9 / 0.77: far points whose small cap falls between the
    quadrature rings of neighbouring samples), so the bounds hold the rms and the 95th percentile."""
    q = off_grid_points(rng, 300, 1.5, 6.0)
    direct = project_visibility(RayCaster([SPHERE]), q, ORDER, degree=QUICK["degree"])
    err = relative_to_shadow(sphere_oof.lookup(q), direct)
    assert np.sqrt(np.mean(err**2)) < 0.3 and np.percentile(err, 95) < 0.6


@pytest.mark.slow
def test_interpolation_error_off_grid_default_grid(rng):
    oof = occlusion_field(SPHERE, ORDER)
    q = off_grid_points(rng, 300, 1.5, 6.0)
    direct = project_visibility(RayCaster([SPHERE]), q, ORDER)
    err = relative_to_shadow(oof.lookup(q), direct)
    assert np.sqrt(np.mean(err**2)) < 0.13 and np.percentile(err, 95) < 0.25
    err = relative_to_shadow(oof.lookup(q), cap_visibility(q))
    assert np.sqrt(np.mean(err**2)) < 0.12


def test_moved_object_matches_ray_casting_in_its_pose(rng):
    """A posed (rotated, scaled, translated) asymmetric object: lookup with its transform against a
    direct projection in the world frame, within the documented interpolation bound."""
    box = builtin_mesh("box", size=[1.0, 0.4, 0.2])
    oof = occlusion_field(box, ORDER, **QUICK)
    pose = Transform(translate=np.array([0.3, -1.0, 2.0]), rotate_deg=np.array([20.0, 35.0, -50.0]), scale=1.7)
    q = pose.translate + off_grid_points(rng, 200, 1.6, 3.0)
    direct = project_visibility(RayCaster([box], [pose]), q, ORDER, degree=QUICK["degree"])
    err = relative_to_shadow(oof.lookup(q, pose), direct)
    assert np.sqrt(np.mean(err**2)) < 0.3
    # the rotation is the SH rotation of the object-space lookup
    local = ((q - pose.translate) @ pose.rotation) / pose.scale
    np.testing.assert_allclose(oof.lookup(q, pose), sh.rotate(oof.lookup(local), pose.rotation), atol=1e-12)


def test_lookup_tiers_agree(sphere_oof, rng):
    q = off_grid_points(rng, 50, 0.1, 10.0)
    pose = Transform(rotate_deg=np.array([10.0, 0.0, 0.0]))
    np.testing.assert_allclose(sphere_oof.lookup(q, pose), sphere_oof.lookup(q, pose, method="reference"),
                               atol=1e-12)


def test_beyond_outermost_sphere_is_unoccluded(sphere_oof):
    far = np.array([[0.0, 0.0, 9.0], [20.0, 0.0, 0.0]])
    np.testing.assert_array_equal(sphere_oof.lookup(far), np.tile(ONE, (2, 1)))


def test_self_visibility_of_a_convex_object_is_the_outer_hemisphere():
    """The outer hemisphere about each vertex normal, reached at the step function's quadrature rate."""
    n = np.asarray(SPHERE.vertex_normals)
    ref = sh.zh_rotate(sh.blocker_zh(np.full(len(n), np.pi / 2), ORDER), -n)
    rms = [np.sqrt(np.mean(relative_to_shadow(self_visibility(SPHERE, ORDER, degree=d), ref) ** 2))
           for d in (31, 63, 127)]
    assert rms[1] <= STEP_RATE * rms[0] and rms[2] <= STEP_RATE * rms[1], rms


def test_self_visibility_of_a_plane_is_one():
    plane = builtin_mesh("plane", size=[2, 2], resolution=[2, 2])
    np.testing.assert_allclose(self_visibility(plane, 2, degree=7), np.tile(ONE[:4], (9, 1)), atol=1e-12)


def test_shapes_empty_and_round_trip(sphere_oof):
    assert sphere_oof.coeffs.shape == (8, 6, 8, 8, 16)
    assert sphere_oof.lookup(np.zeros((0, 3))).shape == (0, 16)
    assert sphere_oof.lookup(np.zeros((2, 2, 3)) + 3.0).shape == (2, 2, 16)
    back = OcclusionField.from_arrays(sphere_oof.to_arrays())
    np.testing.assert_array_equal(back.coeffs, sphere_oof.coeffs)
    assert back.order == ORDER


def test_numpy_ray_tier_agrees(rng):
    small = builtin_mesh("icosphere", subdivisions=1)
    q = off_grid_points(rng, 5, 1.5, 3.0)
    a = project_visibility(RayCaster([small]), q, 2, degree=11)
    b = project_visibility(RayCaster([small]), q, 2, degree=11, method="numpy")
    np.testing.assert_allclose(a, b, atol=1e-12)


def test_errors(sphere_oof):
    caster = RayCaster([SPHERE])
    with pytest.raises(TypeError, match="order must be an int"):
        occlusion_field(SPHERE, 2.0)
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        project_visibility(caster, np.zeros((1, 3)), 0)
    with pytest.raises(ValueError, match="degree must be an int >= "):
        project_visibility(caster, np.zeros((1, 3)), 4, degree=3)
    with pytest.raises(ValueError, match="origins must be a"):
        project_visibility(caster, np.zeros((1, 2)), 2)
    with pytest.raises(ValueError, match="origins contain NaN"):
        project_visibility(caster, [[np.nan, 0, 0]], 2)
    with pytest.raises(TypeError, match="mesh must be a trimesh"):
        occlusion_field("sphere.ply")
    with pytest.raises(ValueError, match="normals are required"):
        self_visibility((SPHERE.vertices, SPHERE.faces), 2)
    with pytest.raises(ValueError, match="one per vertex"):
        self_visibility(SPHERE, 2, normals=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="points must be a"):
        sphere_oof.lookup(np.zeros(3)[:2])
    with pytest.raises(ValueError, match="points contains NaN or inf"):
        sphere_oof.lookup([[np.nan, 0.0, 0.0]])
