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
from prtlab.geometry._spheremaps import _face_directions
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


def _face_points(face, s, t):
    """Unit directions of continuous cubemap face coordinates (extended linearly beyond a face's edges)."""
    sc, tc = 2.0 * s - 1.0, 2.0 * t - 1.0
    out = np.empty(s.shape + (3,))
    for f in range(6):
        m = face == f
        out[m] = _face_directions(f, sc[m], tc[m])
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def trilinear_error_bound(grid, field, q, h=1e-2):
    """A priori bound on ``|| I field(q) - field(q) ||`` for the grid's trilinear lookup of a smooth ``field``.

    In the lookup's index coordinates (fractional sphere index, texel column, texel row; unit cells) the
    blend is a tensor product of 1-D linear interpolations, each a convex combination, so the error is at
    most the sum over the axes of the 1-D errors: ``t (1 - t) / 2 * max ||d^2 f / dx_i^2||`` on an
    interpolated axis (the Peano kernel of linear interpolation) and ``|x_i - clamp(x_i)| * max ||df / dx_i||``
    on an axis clamped at a face border. The maxima are taken over 3 x 3 x 3 points of the cell and ``q``
    (central differences of step ``h``). Only for cells that lie wholly where ``field`` is smooth.
    """
    rpos, face, s, t, _ = grid.locate(q)
    g, radii = grid.resolution, grid.radii
    k = np.clip(np.floor(rpos).astype(np.int64), 0, len(radii) - 2)
    coords = np.stack([rpos, s * g - 0.5, t * g - 0.5], axis=-1)
    lo = np.stack([k.astype(float), np.zeros(len(q)), np.zeros(len(q))], axis=-1)
    hi = np.stack([k + 1.0, np.full(len(q), g - 1.0), np.full(len(q), g - 1.0)], axis=-1)
    clamped = np.clip(coords, lo, hi)
    base = np.floor(np.minimum(clamped, hi - 1e-9))

    def f(c):  # the radius is affine in the sphere index within the cell
        r = radii[k] + (c[:, 0] - k) * (radii[k + 1] - radii[k])
        return field(grid.center + r[:, None] * _face_points(face, (c[:, 1] + 0.5) / g, (c[:, 2] + 0.5) / g))

    samples = [base + np.array(o) for o in np.ndindex(3, 3, 3)]
    samples = [base + 0.5 * (p - base) for p in samples] + [coords]
    bound = np.zeros(len(q))
    for axis in range(3):
        step = h * np.eye(3)[axis]
        d1 = d2 = np.zeros(len(q))
        for p in samples:
            fm, f0, fp = f(p - step), f(p), f(p + step)
            d2 = np.maximum(d2, np.linalg.norm(fp - 2.0 * f0 + fm, axis=-1) / h**2)
            d1 = np.maximum(d1, np.linalg.norm(fp - fm, axis=-1) / (2.0 * h))
        frac = clamped[:, axis] - base[:, axis]
        beyond = np.abs(coords[:, axis] - clamped[:, axis])
        bound += np.where(beyond > 0, beyond * d1, 0.5 * frac * (1.0 - frac) * d2)
    return bound


def check_against_the_cap(oof, local, cap):
    """``|| lookup - cap ||`` at object-space points within the trilinear bound of the closed form plus the
    largest error of the blended samples themselves (quadrature and tessellation, held by the tests above):
    the lookup of ``cap + e`` errs by ``(I cap - cap) + I e``, and ``I`` is a convex blend."""
    corners, _, _ = oof.grid.trilinear_corners(local)
    nodes = oof.grid.points().reshape(-1, 3)[corners]
    node_error = np.linalg.norm(oof.coeffs.reshape(-1, oof.coeffs.shape[-1])[corners] - cap(nodes), axis=-1)
    bound = trilinear_error_bound(oof.grid, cap, local) + node_error.max(axis=1)
    err = np.linalg.norm(oof.lookup(local) - cap(local), axis=-1)
    assert np.all(err <= bound), np.max(err / bound)
    return err, bound


def outside_points(grid, rng, n, lo, hi, blocker_radius=1.0):
    """Object-space points ``lo..hi`` bounding radii from the grid's centre whose interpolation cell lies
    wholly outside the blocker (the visibility is smooth there; across the blocker's surface it is not,
    and no bound holds)."""
    q = grid.center + grid.radius * off_grid_points(rng, n, lo, hi)
    rpos = grid.locate(q)[0]
    return q[grid.radii[np.clip(np.floor(rpos).astype(np.int64), 0, len(grid.radii) - 2)] > blocker_radius]


def test_interpolation_error_off_grid(sphere_oof, rng):
    """The trilinear lookup of the quick grid (8 radii, 6 x 8 x 8) at off-grid points 1.5..6 radii away
    stays within :func:`trilinear_error_bound` of the closed-form cap plus the error of the blended samples
    (figures in docs/notes/shadowfields.md)."""
    q = outside_points(sphere_oof.grid, rng, 300, 1.5, 6.0)
    assert len(q) > 250
    # the bound holds for the closed form's own interpolation (a check of the bound's derivation)
    corners, weights, _ = sphere_oof.grid.trilinear_corners(q)
    blend = np.einsum("qc,qcf->qf", weights, cap_visibility(sphere_oof.grid.points().reshape(-1, 3)[corners]))
    assert np.all(np.linalg.norm(blend - cap_visibility(q), axis=-1)
                  <= trilinear_error_bound(sphere_oof.grid, cap_visibility, q))
    check_against_the_cap(sphere_oof, q, cap_visibility)


@pytest.mark.slow
def test_interpolation_error_off_grid_default_grid(rng):
    """As above on the default grid (16 radii, 6 x 16 x 16, default degree)."""
    oof = occlusion_field(SPHERE, ORDER)
    check_against_the_cap(oof, outside_points(oof.grid, rng, 300, 1.5, 6.0), cap_visibility)


def test_moved_object_matches_the_cap_in_its_pose(rng):
    """A posed (rotated, scaled, translated) sphere whose centre is off the object's origin, so the rotation
    moves it: lookup with the transform against the closed-form cap at its world centre and radius equals
    the object-space error (the SH rotation is an isometry), which is within the trilinear bound."""
    offset = np.array([0.5, 0.0, 0.0])
    mesh = SPHERE.copy()
    mesh.vertices = mesh.vertices + offset
    oof = occlusion_field(mesh, ORDER, **QUICK)
    pose = Transform(translate=np.array([0.3, -1.0, 2.0]), rotate_deg=np.array([20.0, 35.0, -50.0]), scale=1.7)
    local = outside_points(oof.grid, rng, 200, 1.6, 3.0)
    q = pose.translate + pose.scale * local @ pose.rotation.T
    world_err = np.linalg.norm(oof.lookup(q, pose) - cap_visibility(q, pose.translate + pose.scale * pose.rotation
                                                                    @ offset, pose.scale), axis=-1)
    err, _ = check_against_the_cap(oof, local, lambda p: cap_visibility(p, offset))
    np.testing.assert_allclose(world_err, err, rtol=1e-9, atol=1e-12)
    # the rotation is the SH rotation of the object-space lookup
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
