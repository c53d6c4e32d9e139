"""SH shadow fields of a whole scene (tests/shadowfields/sh_scene.py): direct shadows from one occluder
against Monte Carlo.

Goal: relative RMS of per-vertex direct light 5 % (issue 15's goal for direct and total light, as the
interreflection tests), against a dense deterministic quadrature of the same integral (``dense_direct``,
degree 127 = 64 x 128 rays per vertex) and against Monte Carlo with the noise in quadrature
(:func:`prtlab.compare`). On this scene (a 4 x 4 floor, a ball of radius 0.5 at height 1, Preetham sky)
the quick fields (8 radii, 6 x 8 x 8, degree 31) give 1.8 % (floor) and 3.0 % (ball) against the
dense quadrature.
"""

from __future__ import annotations

import numpy as np
import pytest

from prtlab import sh
from prtlab.geometry import RayCaster
from prtlab.reference import direct
from prtlab.scene import Scene
from tests.scenes import ball_over_floor
from tests.shadowfields.sh_scene import direct_environment, precompute_scene, scene_visibility, separable_brdfs

ORDER = 4
GOAL = 0.05
#: Monte Carlo samples per vertex: relative noise 0.008 (floor), 0.013 (ball), within a third of the goal
SAMPLES = 2048
QUICK = dict(n_radii=8, resolution=8, degree=31)


def dense_direct(scene, degree=127):
    """Deterministic ground truth of diffuse direct light: product quadrature with ray-cast visibility."""
    caster = RayCaster(scene)
    dirs, w = sh.quadrature(1, degree)
    radiance = scene.environment.radiance(dirs)
    out = {}
    for o in scene.objects:
        x, n = o.world_vertices(), o.world_normals()
        occ = caster.occluded(x[:, None, :], dirs[None], np.inf, normals=n[:, None, :])
        cos = np.maximum(n @ dirs.T, 0.0)
        out[o.name] = np.einsum("vd,d,dc->vc", ~occ * cos, w, radiance) * o.material.albedo / np.pi
    return out


@pytest.fixture(scope="module")
def shaded():
    scene = ball_over_floor()
    data = precompute_scene(scene, ORDER, **QUICK)
    vis = scene_visibility(scene, data)
    return scene, data, vis, direct_environment(scene, vis, separable_brdfs(scene), ORDER)


def test_sh_error_against_dense_quadrature_is_within_the_documented_bound(shaded):
    scene, _, _, rad = shaded
    truth = dense_direct(scene)
    for name, value in rad.items():
        b = truth[name]
        assert np.sqrt(np.mean((value - b) ** 2)) / np.sqrt(np.mean(b**2)) < GOAL, name


def test_direct_shadows_against_monte_carlo(shaded):
    """Every object's direct light within ``GOAL`` of Monte Carlo (``SAMPLES`` per vertex), noise in quadrature."""
    import types

    import prtlab

    scene, _, _, rad = shaded
    ref = direct(scene, SAMPLES, np.random.default_rng(3))
    comparison = prtlab.compare(types.SimpleNamespace(direct=rad), ref, objects=list(rad), parts=["direct"])
    failures = comparison.check(GOAL)
    assert not failures, failures
    # the shadow is there: floor below the ball darker than the floor's corners
    floor = rad["floor"]
    x = scene.object("floor").world_vertices()
    r = np.linalg.norm(x[:, [0, 2]], axis=1)
    assert floor[r < 0.3].mean() < 0.8 * floor[r > 1.5].mean()


def test_rotating_an_object_rotates_its_fields(shaded):
    """A ball is round: turning it (its occlusion field rotated by SH rotation) changes the floor's visibility
    by at most the two lookups' distances from the ball's closed-form cap (triangle inequality), each held
    within the a-priori trilinear bound plus its nodes' error by :func:`check_against_the_cap`."""
    from prtlab.scene import Transform
    from prtlab.shadowfields import OcclusionField
    from tests.shadowfields.test_occlusion import cap_visibility, check_against_the_cap

    scene, data, vis, _ = shaded
    turned = Transform(translate=np.array([0, 1.0, 0]), rotate_deg=np.array([0.0, 0.0, 0.0]))
    same = scene_visibility(scene, data, {"ball": turned})
    np.testing.assert_allclose(same["floor"], vis["floor"], atol=1e-12)
    rot = Transform(translate=np.array([0, 1.0, 0]), rotate_deg=np.array([30.0, 70.0, 10.0]))
    moved = scene_visibility(scene, data, {"ball": rot})
    x = scene.object("floor").world_vertices()
    # the floor does not shadow itself, so its visibility is the ball's lookup alone
    oof = OcclusionField.from_arrays(data["ball"]["oof"])
    np.testing.assert_allclose(moved["floor"], oof.lookup(x, rot), atol=1e-12)
    cap = lambda p: cap_visibility(p, np.zeros(3), 0.5)  # noqa: E731 - the ball's mesh, object space
    err_still, _ = check_against_the_cap(oof, x - turned.translate, cap)
    err_turned, _ = check_against_the_cap(oof, (x - rot.translate) @ rot.rotation, cap)
    shadow = np.linalg.norm(vis["floor"] - moved["floor"], axis=1)
    assert np.all(shadow <= err_still + err_turned + 1e-12)
    assert np.max(shadow) > 0.0  # the lookups did move: the check is not of one field against itself


def test_reference_tier_of_the_lookups_agrees(shaded):
    scene, data, vis, _ = shaded
    ref = scene_visibility(scene, data, method="reference")
    for name in vis:
        np.testing.assert_allclose(ref[name], vis[name], atol=1e-10)


def test_no_environment_gives_zero(shaded):
    scene, _, vis, _ = shaded
    dark = Scene(objects=scene.objects, lights=[], camera=scene.camera)
    out = direct_environment(dark, vis, separable_brdfs(dark), ORDER)
    assert all(np.all(v == 0) for v in out.values())


def dense_direct_glossy(scene, obj, degree=127):
    """Deterministic ground truth of direct light on one object with its exact BRDF toward the camera."""
    from prtlab import brdf

    caster = RayCaster(scene)
    dirs, w = sh.quadrature(1, degree)
    radiance = scene.environment.radiance(dirs)
    x, n = obj.world_vertices(), obj.world_normals()
    occ = caster.occluded(x[:, None, :], dirs[None], np.inf, normals=n[:, None, :])
    wo = scene.camera.position - x
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    f = brdf.from_material(obj.material).eval(dirs[None], wo[:, None], n[:, None])
    return np.einsum("vd,d,dc,vdc->vc", ~occ * np.maximum(n @ dirs.T, 0.0), w, radiance, f)


@pytest.fixture(scope="module")
def glossy():
    """The Phong floor (kd 0.3, ks 0.5, exponent 10) toward the camera: the dense truth with the exact BRDF
    and the relative RMS error of the order-4 SH shading with K = 1 and K = 4 separable terms."""
    scene = ball_over_floor({"type": "phong", "kd": [0.3, 0.3, 0.3], "ks": [0.5, 0.5, 0.5], "exponent": 10.0})
    vis = scene_visibility(scene, precompute_scene(scene, ORDER, **QUICK))
    truth = dense_direct_glossy(scene, scene.object("floor"))
    err = {}
    for K in (1, 4):
        ours = direct_environment(scene, vis, separable_brdfs(scene, K_glossy=K), ORDER)["floor"]
        err[K] = np.sqrt(np.mean((ours - truth) ** 2)) / np.sqrt(np.mean(truth**2))
    return scene, truth, err


def test_glossy_dense_truth_agrees_with_monte_carlo(glossy):
    """The dense truth against an independent Monte Carlo estimate (64 samples per vertex): the mean of the
    squared z-scores over the floor's vertices is that of Student's t with 63 degrees of freedom,
    ``nu / (nu - 2)``, within ``MC_SIGMAS`` standard deviations of a mean of N values
    (``Var t^2 = 2 nu^2 (nu - 1) / ((nu - 2)^2 (nu - 4))``)."""
    from tests.conftest import MC_SIGMAS

    scene, truth, _ = glossy
    n = 64
    ref = direct(scene, n, np.random.default_rng(1))
    z = ((ref.direct["floor"] - truth) / ref.stderr["direct"]["floor"]).ravel()
    nu = n - 1.0
    mean, var = nu / (nu - 2.0), 2.0 * nu**2 * (nu - 1.0) / ((nu - 2.0) ** 2 * (nu - 4.0))
    # the three colour channels of a vertex share their samples: N counts vertices, not channels
    half_width = MC_SIGMAS * np.sqrt(var / (z.size / 3))
    assert abs(np.mean(z**2) - mean) < half_width, (np.mean(z**2), mean, half_width)


def test_glossy_receiver_more_separable_terms_help(glossy):
    """Four separable terms err less than one (the separable part of the error falls with K, the rest is
    shared). Measured figures: docs/notes/shadowfields.md."""
    _, _, err = glossy
    assert err[4] < err[1], err


@pytest.mark.xfail(strict=True, reason="measured 0.081 (K = 4; 0.185 with K = 1) vs goal 0.05: order-4 SH "
                                       "cannot carry a Phong exponent-10 lobe (transfer error of the 4-term "
                                       "BRDF at order 4: 0.34, prtlab.brdf.transfer_error)")
def test_glossy_receiver_through_the_separable_brdf_within_the_goal(glossy):
    """The Phong floor's direct light (K = 4) within ``GOAL`` of the dense truth."""
    _, _, err = glossy
    assert err[4] < GOAL, err
