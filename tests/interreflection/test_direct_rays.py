"""Direct light by shadow rays (prtlab/interreflection/_direct_rays.py, ``shadows="rays"``).

The estimator of an area light is ``A / m sum_j F(y_j)`` over ``m`` points of a grid jittered per vertex;
stratification never raises the variance above that of ``m`` independent uniform points, so each vertex is
within ``MC_SIGMAS * sqrt(Var F / m)`` of the integral, ``Var F = A int F^2 dA - (int F dA)^2`` (both by a
Gauss-Legendre rule over the light, whose own error is bounded by the difference of two rules). A point
light's visibility is held to a segment-box test written here (slabs), independent of Embree.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prtlab import brdf
from prtlab.cache import cache_key
from prtlab.geometry import RayCaster, builtin_mesh
from prtlab.interreflection import Interreflection, InterreflectionOptions
from prtlab.interreflection._direct_rays import (jitter, light_terms, light_terms_reference, mirror_wo,
                                                ray_traced_direct, ray_traced_direct_reference, sample_count,
                                                widened_sphere)
from prtlab.scene import AreaLight, Material, PointLight, Transform
from tests.conftest import MC_SIGMAS
from tests.scenes import floor_and_ball

LIGHT = AreaLight(center=np.array([0.3, 2.5, 0.4]), u=np.array([0.3, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.3]),
                  radiance=np.array([30.0, 20.0, 10.0]))


def _floor_points(n=7, size=3.0):
    s = np.linspace(-size / 2, size / 2, n)
    x, z = np.meshgrid(s, s)
    points = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], axis=1)
    return points, np.tile([0.0, 1.0, 0.0], (len(points), 1))


def _moments(light, factor, points, normals, n_nodes):
    """``(int F dA, int F^2 dA)`` (V, J) of the area-light integrand ``F = q_j(w) cos_x cos_l / d^2`` (unit
    radiance; ``factor(w)`` (V, P, J) gives ``q``), by a tensor Gauss-Legendre rule over the parallelogram."""
    t, w = np.polynomial.legendre.leggauss(n_nodes)
    s_, t_ = np.meshgrid(t, t, indexing="ij")
    y = light.center + s_.reshape(-1, 1) * light.u + t_.reshape(-1, 1) * light.v
    dA = np.outer(w, w).ravel() * np.linalg.norm(np.cross(light.u, light.v))
    d = y[None] - points[:, None]
    r2 = np.sum(d * d, axis=-1)
    wy = d / np.sqrt(r2)[..., None]
    F = (np.maximum(np.einsum("vpi,vi->vp", wy, normals), 0.0) * np.maximum(-(wy @ light.normal), 0.0) / r2)[..., None]
    F = F * factor(wy)
    return np.einsum("vpk,p->vk", F, dA), np.einsum("vpk,p->vk", F**2, dA)


@pytest.mark.parametrize("material", [Material(albedo=np.array([0.7, 0.6, 0.5])),
                                      Material(type="phong", kd=np.array([0.3] * 3), ks=np.array([0.5] * 3),
                                               exponent=10.0)], ids=["lambert", "phong"])
@pytest.mark.parametrize("samples", [16, 256])
def test_an_unoccluded_area_light_is_its_integral_within_the_estimators_error(material, samples):
    """Both outputs, ``L_k`` (the separable terms ``g_k``) and the radiance toward the viewer (the BRDF
    itself), each within the estimator's standard error bound of the integral."""
    f = brdf.from_material(material)
    sep = brdf.separable(f, K=4 if material.type == "phong" else 1)
    points, normals = _floor_points()
    wo = np.array([0.2, 1.0, 0.9]) - 0.1 * points
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    caster = RayCaster(builtin_mesh("icosphere", subdivisions=1), transforms=[Transform(translate=[0, -50, 0])])
    light_k, radiance = ray_traced_direct(points, normals, wo, f, sep, caster, [LIGHT], samples)
    m = int(np.sqrt(samples)) ** 2

    def integral_and_bound(factor):
        first, second = _moments(LIGHT, factor, points, normals, 48)
        quadrature = np.abs(first - _moments(LIGHT, factor, points, normals, 24)[0])
        sigma = np.sqrt(np.maximum(LIGHT.area * second - first**2, 0.0) / m)
        assert np.all(first[:, 0] > 0.0)  # every point sees the light: the check is not of zeros
        return first, MC_SIGMAS * sigma + quadrature

    first, bound = integral_and_bound(lambda w: sep.g(brdf.to_local(w, np.broadcast_to(normals[:, None], w.shape))))
    assert np.all(np.abs(light_k - first[..., None] * LIGHT.radiance) <= bound[..., None] * LIGHT.radiance + 1e-12)
    first, bound = integral_and_bound(lambda w: f.eval(w, wo[:, None], normals[:, None]))  # (V, P, C)
    assert np.all(np.abs(radiance - first * LIGHT.radiance) <= bound * LIGHT.radiance + 1e-12)


def test_a_lambertian_vertex_seen_from_behind_keeps_its_radiance():
    """The camera below a floor: its Lambertian radiance is the same as seen from above (two-sided BRDF)."""
    f = brdf.from_material(Material(albedo=np.array([0.7, 0.6, 0.5])))
    sep = brdf.separable(f, K=1)
    points, normals = _floor_points()
    caster = RayCaster(builtin_mesh("icosphere", subdivisions=1), transforms=[Transform(translate=[0, -50, 0])])
    above = ray_traced_direct(points, normals, normals, f, sep, caster, [LIGHT], 16)
    below = ray_traced_direct(points, normals, -normals, f, sep, caster, [LIGHT], 16)
    np.testing.assert_array_equal(below[1], above[1])
    np.testing.assert_allclose(above[1], np.einsum("vkc,kc->vc", above[0], sep.colour), rtol=1e-12)
    assert np.all(above[1] > 0.0)


def _segment_hits_box(a, b, lo, hi) -> np.ndarray:
    """Whether the open segments ``a -> b`` (V, 3) meet the axis-aligned box ``[lo, hi]`` (slab test)."""
    d = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - a) / d, (hi - a) / d
    near = np.nanmax(np.where(d == 0, np.where((a >= lo) & (a <= hi), -np.inf, np.inf), np.minimum(t0, t1)), axis=1)
    far = np.nanmin(np.where(d == 0, np.where((a >= lo) & (a <= hi), np.inf, -np.inf), np.maximum(t0, t1)), axis=1)
    return (near <= far) & (far > 0.0) & (near < 1.0)


def test_a_point_light_is_shadowed_exactly_by_a_moved_box():
    """Points on a floor under a point light, a 0.6 m box moved there by its transform: a point is dark
    exactly when its segment to the light meets the box (points near the shadow's edge left out)."""
    sep = brdf.separable(brdf.from_material(Material(albedo=np.array([0.7, 0.7, 0.7]))), K=1)
    points, normals = _floor_points(41, 4.0)
    light = PointLight(position=np.array([0.2, 3.0, -0.1]), intensity=np.array([5.0, 4.0, 3.0]))
    box = builtin_mesh("box", size=[0.6, 0.6, 0.6])
    pose = Transform(translate=np.array([0.5, 1.0, 0.3]))
    caster = RayCaster([box], transforms=[pose])
    f = brdf.from_material(Material(albedo=np.array([0.7, 0.7, 0.7])))
    ours = ray_traced_direct(points, normals, normals, f, sep, caster, [light], 1)[0][:, 0, 0]
    d = light.position - points
    r2 = np.sum(d * d, axis=1)
    lit = light.intensity[0] * (d[:, 1] / np.sqrt(r2)) / r2 / np.pi  # g = 1 / pi for a Lambertian term
    lo, hi = pose.translate - 0.3, pose.translate + 0.3
    dark = _segment_hits_box(points, np.broadcast_to(light.position, points.shape), lo, hi)
    clear = ~_segment_hits_box(points, np.broadcast_to(light.position, points.shape), lo - 0.02, hi + 0.02)
    inside = _segment_hits_box(points, np.broadcast_to(light.position, points.shape), lo + 0.02, hi - 0.02)
    assert inside.sum() >= 20 and clear.sum() >= 200
    np.testing.assert_allclose(ours[inside], 0.0, atol=0.0)
    np.testing.assert_allclose(ours[clear], lit[clear], rtol=1e-12)
    assert np.all(dark[inside])
    # a small area light there: a point whose segments to its four corners all meet the convex box sees none
    # of it (the box's shadow on the light's plane is convex and holds the corners)
    small = AreaLight(center=light.position, u=np.array([0.1, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.1]),
                      radiance=np.array([1.0, 1.0, 1.0]))
    area = ray_traced_direct(points, normals, normals, f, sep, caster, [small], 64)[0][:, 0, 0]
    corners = [small.center + a * small.u + b * small.v for a in (-1, 1) for b in (-1, 1)]
    umbra = np.all([_segment_hits_box(points, np.broadcast_to(c, points.shape), lo + 0.02, hi - 0.02)
                    for c in corners], axis=0)
    assert umbra.sum() >= 10
    np.testing.assert_array_equal(area[umbra], 0.0)
    assert np.all(area[clear & ~dark] > 0.0)


def test_rays_precompute_what_sh_does_and_take_point_lights():
    scene = floor_and_ball()
    def key(scene, options):
        return cache_key(*Interreflection.cache_key_parts(scene, options))

    assert key(scene, InterreflectionOptions(shadows="rays")) == key(scene, InterreflectionOptions(shadows="sh"))
    assert key(scene, InterreflectionOptions(light_samples=16)) == key(scene, InterreflectionOptions())
    light = [PointLight(position=np.array([0.0, 3.0, 0.0]), intensity=np.array([1.0, 1.0, 1.0]))]
    Interreflection.check_lights(light, InterreflectionOptions(shadows="rays"))
    with pytest.raises(ValueError, match="shadows='rays' or 'haar'"):
        Interreflection.check_lights(light, InterreflectionOptions(shadows="sh"))
    with pytest.raises(ValueError, match="light_samples"):
        InterreflectionOptions(light_samples=0)


# ------------------------------------------------------------------ the numba kernel and the reference tier

def _tier_scene():
    """Points on a 4 m floor (every fifth normal facing down, every seventh tilted), view directions some below
    the horizon, a box and a ball casting shadows, two static specks fixing the casters' bounding box (so their
    ray offsets stay when the box moves), and an area light, a tilted one and a point light."""
    points, normals = _floor_points(25, 4.0)
    normals[::5] *= -1.0
    normals[::7] = normals[::7] + [0.3, 0.0, -0.2]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    wo = np.random.default_rng(5).normal(size=points.shape)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    meshes = [builtin_mesh("box", size=[0.6, 0.6, 0.6]), builtin_mesh("icosphere", radius=0.3, subdivisions=2),
              builtin_mesh("icosphere", radius=0.05, subdivisions=0), builtin_mesh("icosphere", radius=0.05,
                                                                                   subdivisions=0)]
    poses = [Transform(translate=np.array([0.5, 1.0, 0.3])), Transform(translate=np.array([-0.8, 0.6, -0.5])),
             Transform(translate=np.array([-4.0, -1.0, -4.0])), Transform(translate=np.array([4.0, 5.0, 4.0]))]
    tilted = AreaLight(center=np.array([-1.0, 2.0, 1.0]), u=np.array([0.2, 0.1, 0.0]), v=np.array([0.0, 0.1, 0.25]),
                       radiance=np.array([3.0, 4.0, 5.0]))
    point = PointLight(position=np.array([0.2, 3.0, -0.1]), intensity=np.array([5.0, 4.0, 3.0]))
    return points, normals, wo, meshes, poses, [LIGHT, tilted, point]


#: The box's pose after the move of the re-cast tests
MOVED_BOX = Transform(translate=np.array([0.1, 0.9, 0.6]), rotate_deg=np.array([0.0, 30.0, 0.0]))


def _before_and_after_a_move():
    """:func:`_tier_scene`'s points, normals, view directions (mirrored, :func:`mirror_wo`), meshes and lights, its
    casters before and after the box moves to ``MOVED_BOX``, and the box's widened bounding spheres at both poses
    (``moved=``)."""
    points, normals, wo, meshes, poses, lights = _tier_scene()
    before = RayCaster(meshes, transforms=poses)
    after = RayCaster(meshes, transforms=[MOVED_BOX, *poses[1:]])
    spheres = [widened_sphere([*p.translate, np.sqrt(3) * 0.3], before.epsilon) for p in (poses[0], MOVED_BOX)]
    return points, normals, mirror_wo(wo, normals), meshes, lights, before, after, spheres


MATERIALS = [Material(albedo=np.array([0.7, 0.6, 0.5])),
             Material(type="phong", kd=np.array([0.3, 0.2, 0.1]), ks=np.array([0.5, 0.4, 0.3]), exponent=10.0)]


@pytest.mark.parametrize("material", MATERIALS, ids=["lambert", "phong"])
def test_the_kernel_equals_the_float64_reference_tier(material):
    """Same samples (the hash of ``jitter``), same rays: the per-light masks are equal and the sums agree to
    1e-12 of their largest value (only the order of float64 roundings differs)."""
    f = brdf.from_material(material)
    sep = brdf.separable(f, K=4 if material.type == "phong" else 1)
    points, normals, wo, meshes, poses, lights = _tier_scene()
    caster = RayCaster(meshes, transforms=poses)
    ours = ray_traced_direct(points, normals, wo, f, sep, caster, lights, 64, seed=3)
    ref = ray_traced_direct_reference(points, normals, wo, f, sep, caster, lights, 64, seed=3)
    for a, b in zip(ours, ref):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-12 * np.abs(b).max())
    wo = mirror_wo(wo, normals)
    for i, light in enumerate(lights):
        S, F, blocked = light_terms(points, normals, wo, f, sep, caster, light, i, 64, seed=3)
        S_ref, F_ref, blocked_ref = light_terms_reference(points, normals, wo, f, sep, caster, light, i, 64, seed=3)
        np.testing.assert_array_equal(blocked, blocked_ref)
        assert blocked.shape == (len(points), sample_count(light, 64)) and blocked.any()
        assert np.any(S[:, 0] > 0.0)  # lit somewhere: not a check of zeros
        np.testing.assert_allclose(S, S_ref, rtol=0.0, atol=1e-12 * np.abs(S_ref).max())
        np.testing.assert_allclose(F, F_ref, rtol=0.0, atol=1e-12 * np.abs(F_ref).max())


def test_the_jitter_hash_is_uniform_and_independent_of_the_rows_asked():
    """The numpy hash: a vertex's numbers do not depend on which other rows are asked (chunks, subsets), and
    they are uniform: the mean of 2 x 10^5 within MC_SIGMAS standard errors (1 / sqrt(12 n)) of 1/2."""
    all_rows = jitter(7, 1, np.arange(3125), 64)
    np.testing.assert_array_equal(jitter(7, 1, np.array([17, 3000]), 64), all_rows[[17, 3000]])
    assert not np.array_equal(jitter(7, 2, np.arange(10), 64), all_rows[:10])  # another light, other numbers
    assert np.all((all_rows >= 0.0) & (all_rows < 1.0))
    assert abs(all_rows.mean() - 0.5) <= MC_SIGMAS / np.sqrt(12.0 * all_rows.size)


@pytest.mark.parametrize("terms", [light_terms, light_terms_reference], ids=["kernel", "reference"])
def test_recasting_the_samples_near_a_moved_object_equals_casting_all(terms):
    """The box moves: the previous mask re-cast only where a sample's segment meets the box's bounding sphere
    before or after (widened) equals casting every sample at the new poses, and most samples were not cast;
    with ``previous`` too (the vertices whose capsule to the light misses the spheres keep their sums).
    Without ``moved`` no ray is cast: the mask of a caster of other geometry gives the same terms."""
    f = brdf.from_material(MATERIALS[1])
    sep = brdf.separable(f, K=4)
    points, normals, wo, meshes, lights, before, after, spheres = _before_and_after_a_move()
    assert before.epsilon == after.epsilon and before.tnear == after.tnear
    for i, light in enumerate(lights):
        old = terms(points, normals, wo, f, sep, before, light, i, 64)
        fresh = terms(points, normals, wo, f, sep, after, light, i, 64)
        assert not np.array_equal(old[2], fresh[2])  # the move changed some shadows
        partial = terms(points, normals, wo, f, sep, after, light, i, 64, visibility=old[2], moved=spheres)
        for a, b in zip(partial, fresh):
            np.testing.assert_array_equal(a, b)
        # with the earlier sums, the vertices none of whose segments can meet the spheres keep their rows
        kept = terms(points, normals, wo, f, sep, after, light, i, 64, visibility=old[2], moved=spheres,
                     previous=old[:2])
        for a, b in zip(kept, fresh):
            np.testing.assert_array_equal(a, b)
        # a new camera from the mask alone: the caster is never asked (this one holds nothing near)
        elsewhere = RayCaster([meshes[2]], transforms=[Transform(translate=np.array([50.0, 0.0, 0.0]))])
        reshaded = terms(points, normals, -wo, f, sep, elsewhere, light, i, 64, visibility=fresh[2])
        direct = terms(points, normals, -wo, f, sep, after, light, i, 64)
        for a, b in zip(reshaded, direct):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("kernel", [True, False], ids=["kernel", "reference"])
@pytest.mark.parametrize("material", MATERIALS, ids=["lambert", "phong"])
def test_light_terms_write_into_out_as_they_return(material, kernel, monkeypatch):
    """``out=``: the rows of a call written into given arrays (here two parts of the points, the second with
    ``first=``, as the pipeline's near hits call it) are the arrays of one call, bit for bit, by the kernel and by
    the reference tier it falls back to; bad ``out`` refused."""
    from prtlab.interreflection import _direct_rays

    if not kernel:
        monkeypatch.setattr(_direct_rays, "_kernel_ready", lambda *args: False)
    f = brdf.from_material(material)
    sep = brdf.separable(f, K=4)
    points, normals, wo, meshes, poses, lights = _tier_scene()
    caster = RayCaster(meshes, transforms=poses)
    one = light_terms(points, normals, wo, f, sep, caster, LIGHT, 0, 16)
    whole = (np.empty_like(one[0]), np.empty_like(one[1]), np.empty_like(one[2]))
    cut = len(points) // 3
    for a, b in ((0, cut), (cut, len(points))):
        got = light_terms(points[a:b], normals[a:b], wo[a:b], f, sep, caster, LIGHT, 0, 16, first=a,
                          out=tuple(w[a:b] for w in whole))
        assert all(g is w_ or np.shares_memory(g, w_) for g, w_ in zip(got, whole))
    for a, b in zip(whole, one):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="out must be C-contiguous arrays of shapes"):
        light_terms(points, normals, wo, f, sep, caster, LIGHT, 0, 16, out=(whole[0][:, :1], whole[1], whole[2]))


def _lambert_arguments():
    """:func:`_tier_scene`'s points, normals and view directions, a Lambertian BRDF and its separable form, and the
    scene's caster: the leading arguments of a :func:`light_terms` call."""
    f = brdf.from_material(MATERIALS[0])
    points, normals, wo, meshes, poses, lights = _tier_scene()
    return points, normals, wo, f, brdf.separable(f, K=1), RayCaster(meshes, transforms=poses)


def test_light_terms_refuse_bad_input():
    points, normals, wo, f, sep, caster = _lambert_arguments()
    with pytest.raises(ValueError, match="must be \\(V, 3\\) arrays of one shape"):
        light_terms(points, normals[:-1], wo, f, sep, caster, LIGHT, 0, 16)
    with pytest.raises(ValueError, match="contain NaN or inf"):
        light_terms(points * np.nan, normals, wo, f, sep, caster, LIGHT, 0, 16)
    with pytest.raises(ValueError, match="visibility must be the \\(625, 16\\) bool mask"):
        light_terms(points, normals, wo, f, sep, caster, LIGHT, 0, 16, visibility=np.zeros((625, 64), bool))
    with pytest.raises(ValueError, match="moved= needs the previous visibility="):
        light_terms(points, normals, wo, f, sep, caster, LIGHT, 0, 16, moved=np.zeros((1, 4)))
    with pytest.raises(ValueError, match="previous must be the"):
        light_terms(points, normals, wo, f, sep, caster, LIGHT, 0, 16, visibility=np.zeros((625, 16), bool),
                    moved=np.zeros((0, 4)), previous=(np.zeros((3, 1)), np.zeros((3, 3))))


# ------------------------------------------------------------------ points without a normal

#: normals with ``n . n == 0`` in float64 (each square underflows, below about 1.5e-162): zero, tiny, subnormal, mixed
NO_NORMALS = np.array([[0.0, 0.0, 0.0], [-0.0, 0.0, -0.0], [1e-200, 1e-200, 1e-200], [5e-324, -1e-310, 1e-163],
                       [0.0, -1.49e-162, 0.0]])


def test_a_normal_is_missing_exactly_where_numpy_refuses_it():
    """``_without_normal`` (the reference tier) and ``_no_normal`` (the kernel) take a normal as missing exactly
    where ``np.linalg.norm`` gives 0 and :func:`prtlab.brdf.local_frame` refuses it: around the underflow of the
    squares (``2^-537.5``, about 1.4917e-162) on one, two and three components, subnormals, zeros."""
    from prtlab.interreflection._direct_rays import _no_normal, _without_normal

    edge = 2.0**-537.5
    values = np.array([0.0, 5e-324, 1e-310, 1e-200, 1e-163, edge * (1 - 1e-15), edge, edge * (1 + 1e-15), 1.5e-162,
                       1e-161, 1e-160, 1e-100, 1.0])
    rng = np.random.default_rng(4)
    normals = rng.choice(values, (2000, 3)) * rng.choice([-1.0, 1.0], (2000, 3))
    missing = _without_normal(normals)
    np.testing.assert_array_equal(missing, np.linalg.norm(normals, axis=1) == 0.0)
    np.testing.assert_array_equal(missing, [_no_normal(*n) for n in normals])
    assert 100 < missing.sum() < 1900  # both kinds, many of each
    with pytest.raises(ValueError, match="normal contains a zero vector"):
        brdf.local_frame(normals[missing][:1])
    assert np.all(np.isfinite(brdf.local_frame(normals[~missing])))


@pytest.mark.parametrize("material", MATERIALS, ids=["lambert", "phong"])
def test_a_point_without_a_normal_gets_no_light_in_both_tiers(material):
    """Points whose normal has ``n . n == 0`` (:data:`NO_NORMALS`) have no live sample in either tier: zero terms
    and an all-False mask, whatever their ``wo`` (here their normal, as the pipeline's near hits pass it), with
    ``probe``, ``exact_lit`` and ``decided`` too; the other points' rows are those of a call without them, bit for
    bit."""
    f = brdf.from_material(material)
    sep = brdf.separable(f, K=4 if material.type == "phong" else 1)
    points, normals, wo, meshes, poses, lights = _tier_scene()
    caster = RayCaster(meshes, transforms=poses)
    wo = mirror_wo(wo, normals)
    bare = np.arange(len(points)) % 4 == 1
    given_normals, given_wo = normals.copy(), wo.copy()
    given_normals[bare] = np.resize(NO_NORMALS, (bare.sum(), 3))
    given_wo[bare] = given_normals[bare]
    decided = np.random.default_rng(2).integers(0, 3, len(points)).astype(np.int8)
    for i, light in enumerate(lights):
        for options in ({}, dict(probe=4, exact_lit=True), dict(decided=decided)):
            tiers = []
            for terms in (light_terms, light_terms_reference):
                ours = terms(points, given_normals, given_wo, f, sep, caster, light, i, 16, seed=1, **options)
                whole = terms(points, normals, wo, f, sep, caster, light, i, 16, seed=1, **options)
                assert all(np.all(np.isfinite(a)) for a in ours[:2])
                for a, b in zip(ours, whole):
                    assert not np.any(a[bare]) and np.all(np.signbit(a[bare]) == 0)  # +0 and False
                    np.testing.assert_array_equal(a[~bare], b[~bare])
                assert np.any(ours[0][~bare])  # lit elsewhere: not a check of zeros
                tiers.append(ours)
            np.testing.assert_array_equal(tiers[0][2], tiers[1][2])


@pytest.mark.parametrize("material", MATERIALS, ids=["lambert", "phong"])
def test_a_point_at_the_point_light_gets_no_light_from_it_in_both_tiers(material):
    """A point exactly at a point light's position (distance 0: no direction to it) gets zero terms and an
    all-False mask in both tiers, as a dead sample; the other points' rows are those of a call without it."""
    f = brdf.from_material(material)
    sep = brdf.separable(f, K=4 if material.type == "phong" else 1)
    points, normals, wo, meshes, poses, lights = _tier_scene()
    caster = RayCaster(meshes, transforms=poses)
    wo = mirror_wo(wo, normals)
    light = next(x for x in lights if isinstance(x, PointLight))
    at = np.arange(len(points)) % 5 == 2
    given = points.copy()
    given[at] = light.position
    tiers = []
    for terms in (light_terms, light_terms_reference):
        ours = terms(given, normals, wo, f, sep, caster, light, 2, 1, seed=1)
        whole = terms(points, normals, wo, f, sep, caster, light, 2, 1, seed=1)
        for a, b in zip(ours, whole):
            assert not np.any(a[at])
            np.testing.assert_array_equal(a[~at], b[~at])
        assert np.any(ours[0][~at])  # lit elsewhere: not a check of zeros
        tiers.append(ours)
    np.testing.assert_array_equal(tiers[0][2], tiers[1][2])
    np.testing.assert_allclose(tiers[0][0], tiers[1][0], rtol=1e-12, atol=0.0)


@pytest.mark.parametrize("terms", [light_terms, light_terms_reference], ids=["kernel", "reference"])
def test_both_tiers_refuse_a_nan_normal_and_a_zero_wo_at_a_normal(terms):
    """A NaN or inf normal (either tier: ``_check``) and a zero or underflowing ``wo`` at a point with a normal (the
    kernel's wrapper with the reference tier's message, which its BRDF gives) are refused alike."""
    points, normals, wo, f, sep, caster = _lambert_arguments()
    for bad in (np.nan, np.inf):
        given = normals.copy()
        given[7, 1] = bad
        with pytest.raises(ValueError, match="contain NaN or inf"):
            terms(points, given, wo, f, sep, caster, LIGHT, 0, 16)
    for bad in (0.0, 1e-200):
        given = wo.copy()
        given[7] = bad
        with pytest.raises(ValueError, match="wo contains a zero vector; every direction must be a unit vector"):
            terms(points, normals, given, f, sep, caster, LIGHT, 0, 16)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), scale=st.sampled_from([1.0, 1e-100, 1e-160, 1.5e-162, 1e-200, 1e-310, 0.0]),
       glossy=st.booleans())
def test_the_kernel_never_returns_nan_for_finite_points_and_normals(seed, scale, glossy):
    """Random points around the scene's casters and lights, normals of length 1 or ``scale`` (tiny, subnormal,
    zero; some components set to 0 or their sign flipped), every sample cast or probed: the kernel's terms are
    finite, and zero with all-False masks exactly at the points without a normal, where the reference tier's are
    too."""
    from prtlab.interreflection._direct_rays import _without_normal

    rng = np.random.default_rng(seed)
    f = brdf.from_material(MATERIALS[1 if glossy else 0])
    sep = brdf.separable(f, K=4 if glossy else 1)
    _, _, _, meshes, poses, lights = _tier_scene()
    caster = RayCaster(meshes, transforms=poses)
    points = rng.uniform([-2.5, -0.5, -2.5], [2.5, 3.0, 2.5], (60, 3))
    normals = rng.normal(size=(60, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals *= np.where(rng.random((60, 1)) < 0.5, scale, 1.0)
    normals[rng.random((60, 3)) < 0.2] = 0.0
    wo = mirror_wo(rng.normal(size=(60, 3)), normals)
    bare = _without_normal(normals)
    wo[bare] *= scale  # any wo at a point without a normal
    for i, light in enumerate(lights):
        for probe in (0, 4):
            S, F, blocked = light_terms(points, normals, wo, f, sep, caster, light, i, 16, seed=seed, probe=probe)
            assert np.all(np.isfinite(S)) and np.all(np.isfinite(F))
            assert not (np.any(S[bare]) or np.any(F[bare]) or np.any(blocked[bare]))
            ref = light_terms_reference(points, normals, wo, f, sep, caster, light, i, 16, seed=seed, probe=probe)
            assert not any(np.any(a[bare]) for a in ref)


def test_the_pipeline_reuses_the_shadow_masks_and_equals_a_fresh_shade():
    """Relighting (the area light's radiance doubles) rescales the kept terms; moving the ball re-casts only
    near it; a new camera reshades from the masks; an equal environment keeps its SH, a new one projects again:
    each frame equals a fresh shade of the same state."""
    from prtlab.pipeline import FrameState

    lights = [{"type": "environment", "constant": [0.2, 0.2, 0.2]},
              {"type": "area", "center": [0.3, 2.5, 0.4], "u": [0.3, 0, 0], "v": [0, 0, 0.3], "radiance": [30, 20, 10]},
              {"type": "point", "position": [-1.0, 2.0, 0.5], "intensity": [2.0, 2.0, 2.0]}]
    scene = floor_and_ball(8, 2, (1.3, 0.7, 1.2), lights=lights, dynamic=True)
    options = dict(n_radii=4, resolution=6, degree=15, n_lights=16, n_basis=4, light_samples=16)
    pre = Interreflection.precompute(scene, options, cache=False, progress=False)
    state = FrameState.from_scene(scene)
    first = pre.shade(state, bounces=0)
    assert first.info["direct_rays_cast"] > 0
    masks = {r: {i: e["mask"] for i, e in entry["lights"].items()} for r, entry in pre.reuse.direct_rays.items()}

    def fresh(state):
        return Interreflection(scene, pre.options, pre.data).shade(state, bounces=0)

    area = state.lights[1]
    state.lights[1] = type(area)(center=area.center, u=area.u, v=area.v, radiance=2.0 * area.radiance)
    relit = pre.shade(state, bounces=0)
    assert all(pre.reuse.direct_rays[r]["lights"][i]["mask"] is m for r in masks for i, m in masks[r].items())
    assert relit.info["direct_rays_cast"] == 0
    np.testing.assert_allclose(relit.direct["floor"], fresh(state).direct["floor"], rtol=1e-12)
    assert np.any(relit.direct["floor"] != first.direct["floor"])
    state.transforms["ball"] = Transform(translate=np.array([1.1, 0.7, 1.3]))  # in the box: same ray offsets
    moved = pre.shade(state, bounces=0)
    # the ball's own samples and the floor's near the ball, not all of the floor's (a full cast skips the floor's
    # samples no blocker is near too: light_terms' blockers=, so it casts about as few here)
    again = fresh(state)
    assert 0 < moved.info["direct_rays_cast"] <= again.info["direct_rays_cast"]
    for name in ("floor", "ball"):
        np.testing.assert_array_equal(moved.direct[name], again.direct[name])
    state.camera = type(scene.camera)(position=np.array([2.0, 3.0, -4.0]), look_at=np.zeros(3))
    turned = pre.shade(state, bounces=0)
    assert turned.info["direct_rays_cast"] == 0
    for name in ("floor", "ball"):
        np.testing.assert_array_equal(turned.direct[name], fresh(state).direct[name])
    coefficients = pre.reuse.environment_sh[2]
    state.lights[0] = dataclasses.replace(state.lights[0], constant=np.array([0.2, 0.2, 0.2]))  # equal: kept
    pre.shade(state, bounces=0)
    assert pre.reuse.environment_sh[2] is coefficients
    state.lights[0] = dataclasses.replace(state.lights[0], constant=np.array([0.1, 0.3, 0.2]))  # new: projected
    brighter = pre.shade(state, bounces=0)
    assert brighter.info["direct_rays_cast"] == 0
    for name in ("floor", "ball"):
        np.testing.assert_array_equal(brighter.direct[name], fresh(state).direct[name])
        assert np.any(brighter.direct[name] != turned.direct[name])


@pytest.mark.parametrize("material", MATERIALS, ids=["lambert", "phong"])
def test_samples_no_blocker_is_near_are_not_cast_and_change_nothing(material):
    """``blockers`` (:func:`blocker_bounds`: the box's and balls' spheres, a wall's slab, the floor receiver's own
    plane left out) skip the rays whose segment meets none of them: masks and sums equal those of casting every
    ray, bit for bit, for every light, with fewer rays; floor points behind the wall still cast theirs."""
    from prtlab.interreflection._direct_rays import blocker_bounds

    f = brdf.from_material(material)
    sep = brdf.separable(f, K=4 if material.type == "phong" else 1)
    points, normals, wo, meshes, poses, lights = _tier_scene()
    plane = builtin_mesh("plane", size=[4.2, 4.2], resolution=[6, 6])
    wall = builtin_mesh("plane", size=[4.2, 2.0], resolution=[4, 2])
    meshes = [plane, wall, *meshes]
    poses = [Transform(), Transform(translate=np.array([0.0, 1.0, -1.2]), rotate_deg=np.array([90.0, 0.0, 0.0])),
             *poses]
    caster = RayCaster(meshes, transforms=poses)
    flat = [True, True, False, False, False, False]
    blockers = blocker_bounds(caster, flat, exclude=0)
    assert blockers[0].shape == (4, 4) and blockers[1].shape == (1, 5)
    wo = mirror_wo(wo, normals)
    for i, light in enumerate(lights):
        every, culled = {}, {}
        full = light_terms(points, normals, wo, f, sep, caster, light, i, 64, seed=3, stats=every)
        fast = light_terms(points, normals, wo, f, sep, caster, light, i, 64, seed=3, stats=culled,
                           blockers=blockers)
        for a, b in zip(fast, full):
            np.testing.assert_array_equal(a, b)
        assert full[2].any() and 0 < culled["rays_cast"] < every["rays_cast"]
        behind = points[:, 2] < -1.25  # their segments to every light cross the wall's plane: all cast
        slab, plain = {}, {}
        light_terms(points[behind], normals[behind], wo[behind], f, sep, caster, light, i, 64, stats=slab,
                    blockers=(np.zeros((0, 4)), blockers[1]))
        light_terms(points[behind], normals[behind], wo[behind], f, sep, caster, light, i, 64, stats=plain)
        assert slab["rays_cast"] == plain["rays_cast"] > 0


@pytest.mark.parametrize("material", MATERIALS, ids=["lambert", "phong"])
def test_packets_give_the_masks_and_sums_of_one_ray_calls(material, monkeypatch):
    """The kernel's shadow rays 16 at a time (``rtcOccluded16``, ``PACKETS``) against one at a time
    (``rtcOccluded1``): masks, sums and ray counts bit for bit, with blockers culling, a partial re-cast after a
    move and a probe, at 64 samples (vertex packets) and 4 (packets across vertices)."""
    from prtlab.interreflection import _direct_rays
    from prtlab.interreflection._direct_rays import blocker_bounds

    f = brdf.from_material(material)
    sep = brdf.separable(f, K=4 if material.type == "phong" else 1)
    points, normals, wo, _, lights, caster, after, spheres = _before_and_after_a_move()
    blockers = blocker_bounds(caster, [False] * 4)
    for i, light in enumerate(lights):
        for samples, extra in ((64, {}), (4, {}), (64, {"blockers": blockers}), (64, {"probe": 16})):
            results = {}
            for packets in (False, True):
                monkeypatch.setattr(_direct_rays, "PACKETS", packets)
                stats = {}
                old = light_terms(points, normals, wo, f, sep, caster, light, i, samples, seed=3, stats=stats, **extra)
                again = light_terms(points, normals, wo, f, sep, after, light, i, samples, seed=3, stats=stats,
                                    visibility=old[2], moved=spheres, previous=old[:2], **extra)
                results[packets] = (*old, *again, stats["rays_cast"])
            assert results[True][-1] > 0 and results[True][2].any()
            for a, b in zip(results[True], results[False]):
                np.testing.assert_array_equal(a, b)


def test_the_probe_mask_spreads_over_the_grid_with_its_corners():
    mask = _direct_rays_probe_mask(LIGHT, 64, 16).reshape(8, 8)
    assert mask.sum() == 16 and mask[0, 0] and mask[0, 7] and mask[7, 0] and mask[7, 7]
    np.testing.assert_array_equal(np.nonzero(mask.any(axis=1))[0], [0, 2, 5, 7])
    assert _direct_rays_probe_mask(LIGHT, 64, 0).shape == (0,)
    assert _direct_rays_probe_mask(LIGHT, 64, 64).shape == (0,)
    assert _direct_rays_probe_mask(PointLight(position=np.zeros(3), intensity=np.ones(3)), 64, 16).shape == (0,)


def _direct_rays_probe_mask(light, samples, probe):
    from prtlab.interreflection._direct_rays import probe_mask

    return probe_mask(light, samples, probe)


@pytest.mark.parametrize("material", MATERIALS, ids=["lambert", "phong"])
def test_a_probe_decides_the_other_samples_where_it_agrees(material):
    """``probe``: the kernel equals the reference tier (masks equal, sums to 1e-12); a vertex whose probes agree
    takes their answer for every other live sample, a vertex whose probes disagree casts them (its mask equal
    to the full cast's there); fewer rays than the full cast; where no sample is shadowed the probe changes
    nothing, bit for bit."""
    f = brdf.from_material(material)
    sep = brdf.separable(f, K=4 if material.type == "phong" else 1)
    points, normals, wo, meshes, poses, lights = _tier_scene()
    caster = RayCaster(meshes, transforms=poses)
    wo = mirror_wo(wo, normals)
    for i, light in enumerate(lights[:2]):
        full_stats, probe_stats = {}, {}
        full = light_terms(points, normals, wo, f, sep, caster, light, i, 64, seed=3, stats=full_stats)
        ours = light_terms(points, normals, wo, f, sep, caster, light, i, 64, seed=3, stats=probe_stats, probe=16)
        ref = light_terms_reference(points, normals, wo, f, sep, caster, light, i, 64, seed=3, probe=16)
        np.testing.assert_array_equal(ours[2], ref[2])
        for a, b in zip(ours[:2], ref[:2]):
            np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-12 * np.abs(b).max())
        assert 0 < probe_stats["rays_cast"] < 0.5 * full_stats["rays_cast"]
        probe = _direct_rays_probe_mask(light, 64, 16)
        # liveness from a caster that blocks nothing: the samples with a weight
        empty = RayCaster([meshes[2]], transforms=[Transform(translate=np.array([50.0, 0.0, 0.0]))])
        unlit = light_terms(points, normals, wo, f, sep, empty, light, i, 64, seed=3)
        lit_full = light_terms(points, normals, wo, f, sep, empty, light, i, 64, seed=3, probe=16)
        for a, b in zip(lit_full, unlit):
            np.testing.assert_array_equal(a, b)
        live = _live(points, normals, light, i)
        n_blocked = np.sum(full[2] & live & probe, axis=1)
        n_lit = np.sum(~full[2] & live & probe, axis=1)
        agreed = (n_lit > 0) != (n_blocked > 0)
        np.testing.assert_array_equal(ours[2][~agreed], full[2][~agreed])
        np.testing.assert_array_equal(ours[2][agreed], (live & (n_blocked > 0)[:, None])[agreed])
        assert np.any(agreed & (n_blocked > 0)) and np.any(~agreed & (n_blocked > 0))


def _live(points, normals, light, index, seed=3):
    """(V, 64) whether a sample of ``light`` faces the vertex and the light, by the reference tier's jitter and
    arithmetic (the unit direction's cosines)."""
    st = (np.stack([a.ravel() for a in np.meshgrid(np.arange(8) / 8, np.arange(8) / 8, indexing="ij")], axis=1)[None]
          + jitter(seed, index, np.arange(len(points)), 64) / 8) * 2.0 - 1.0
    y = light.center + st[..., :1] * light.u + st[..., 1:] * light.v
    d = y - points[:, None]
    w = d / np.linalg.norm(d, axis=-1)[..., None]
    return (np.einsum("vmi,vi->vm", w, normals) > 0.0) & (-w @ light.normal > 0.0)


@pytest.mark.parametrize("terms", [light_terms, light_terms_reference], ids=["kernel", "reference"])
def test_a_probed_recast_after_a_move_equals_a_probed_cast(terms):
    """With ``probe``, the previous mask's bits decided by agreement are cast again where the probes now disagree,
    so a partial re-cast (``visibility``, ``moved``, ``previous``) equals a fresh probed cast bit for bit."""
    f = brdf.from_material(MATERIALS[1])
    sep = brdf.separable(f, K=4)
    points, normals, wo, _, lights, before, after, spheres = _before_and_after_a_move()
    for i, light in enumerate(lights):
        for a_caster, b_caster in ((before, after), (after, before)):
            old = terms(points, normals, wo, f, sep, a_caster, light, i, 64, probe=16)
            fresh = terms(points, normals, wo, f, sep, b_caster, light, i, 64, probe=16)
            partial = terms(points, normals, wo, f, sep, b_caster, light, i, 64, probe=16, visibility=old[2],
                            moved=spheres)
            kept = terms(points, normals, wo, f, sep, b_caster, light, i, 64, probe=16, visibility=old[2],
                         moved=spheres, previous=old[:2])
            for a, b, c in zip(partial, kept, fresh):
                np.testing.assert_array_equal(a, c)
                np.testing.assert_array_equal(b, c)


@pytest.mark.parametrize("material", MATERIALS, ids=["lambert", "phong"])
def test_a_decided_point_takes_its_answer_without_rays(material):
    """``decided``: the kernel equals the reference tier (masks equal, sums to 1e-12), with and without a probe; a
    point given 1 has every sample clear and the sums of a caster that blocks nothing, one given 2 every live sample
    blocked and zero sums, bit for bit; the others are as without ``decided``; only the undecided points cast."""
    f = brdf.from_material(material)
    sep = brdf.separable(f, K=4 if material.type == "phong" else 1)
    points, normals, wo, meshes, poses, lights = _tier_scene()
    caster = RayCaster(meshes, transforms=poses)
    empty = RayCaster([meshes[2]], transforms=[Transform(translate=np.array([50.0, 0.0, 0.0]))])
    wo = mirror_wo(wo, normals)
    decided = (np.arange(len(points)) % 3).astype(np.int8)
    for i, light in enumerate(lights):
        for probe in (0, 16):
            full_stats, stats = {}, {}
            full = light_terms(points, normals, wo, f, sep, caster, light, i, 64, seed=3, stats=full_stats,
                               probe=probe)
            ours = light_terms(points, normals, wo, f, sep, caster, light, i, 64, seed=3, stats=stats, probe=probe,
                               decided=decided)
            ref = light_terms_reference(points, normals, wo, f, sep, caster, light, i, 64, seed=3, probe=probe,
                                        decided=decided)
            np.testing.assert_array_equal(ours[2], ref[2])
            for a, b in zip(ours[:2], ref[:2]):
                np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-12 * np.abs(b).max())
            clear = light_terms(points, normals, wo, f, sep, empty, light, i, 64, seed=3)
            for a, b, c in zip(ours, full, clear):
                np.testing.assert_array_equal(a[decided == 0], b[decided == 0])
                np.testing.assert_array_equal(a[decided == 1], c[decided == 1])
            np.testing.assert_array_equal(ours[0][decided == 2], 0.0)
            np.testing.assert_array_equal(ours[1][decided == 2], 0.0)
            live = clear[1].any(axis=1) if isinstance(light, PointLight) else _live(points, normals, light, i)
            np.testing.assert_array_equal(ours[2][decided == 2], np.broadcast_to(
                live.reshape(len(points), -1), ours[2].shape)[decided == 2])
            assert 0 < stats["rays_cast"] < full_stats["rays_cast"]


@pytest.mark.parametrize("terms", [light_terms, light_terms_reference], ids=["kernel", "reference"])
def test_a_decided_recast_after_a_move_equals_a_decided_cast(terms):
    """With ``decided`` changing between calls (``decided_before``), a partial re-cast (``visibility``, ``moved``,
    ``previous``) equals a fresh cast with the new ``decided`` bit for bit: points decided before and not now are
    cast wholly."""
    f = brdf.from_material(MATERIALS[1])
    sep = brdf.separable(f, K=4)
    points, normals, wo, _, lights, before, after, spheres = _before_and_after_a_move()
    first = (np.arange(len(points)) % 3).astype(np.int8)
    second = (np.arange(len(points)) % 5 % 3).astype(np.int8)
    for i, light in enumerate(lights):
        for probe in (0, 16):
            for a_caster, b_caster in ((before, after), (after, before)):
                old = terms(points, normals, wo, f, sep, a_caster, light, i, 64, probe=probe, decided=first)
                fresh = terms(points, normals, wo, f, sep, b_caster, light, i, 64, probe=probe, decided=second)
                partial = terms(points, normals, wo, f, sep, b_caster, light, i, 64, probe=probe, visibility=old[2],
                                moved=spheres, decided=second, decided_before=first)
                kept = terms(points, normals, wo, f, sep, b_caster, light, i, 64, probe=probe, visibility=old[2],
                             moved=spheres, previous=old[:2], decided=second, decided_before=first)
                for a, b, c in zip(partial, kept, fresh):
                    np.testing.assert_array_equal(a, c)
                    np.testing.assert_array_equal(b, c)


def test_light_terms_refuse_a_bad_decided():
    points, normals, wo, f, sep, caster = _lambert_arguments()
    for terms in (light_terms, light_terms_reference):
        with pytest.raises(ValueError, match="decided must be a"):
            terms(points, normals, wo, f, sep, caster, LIGHT, 0, 16, decided=np.full(len(points), 3))
        with pytest.raises(ValueError, match="decided must be a"):
            terms(points, normals, wo, f, sep, caster, LIGHT, 0, 16, decided=np.zeros(2, int))
        with pytest.raises(ValueError, match="decided_before= needs the visibility="):
            terms(points, normals, wo, f, sep, caster, LIGHT, 0, 16, decided_before=np.zeros(len(points), int))


def test_light_terms_refuse_a_bad_probe():
    points, normals, wo, f, sep, caster = _lambert_arguments()
    for terms in (light_terms, light_terms_reference):
        with pytest.raises(ValueError, match="probe must be a non-negative int"):
            terms(points, normals, wo, f, sep, caster, LIGHT, 0, 16, probe=-1)


def test_the_rays_cast_with_blockers_are_those_whose_segment_meets_one():
    """The kernel tests a sample's segment against the blockers near the vertex's rays alone (its capsule to the
    light): it casts exactly the live samples whose segment meets a blocker's sphere or slab (counted here in numpy
    against every blocker), and every live sample at a vertex inside a sphere."""
    from prtlab.interreflection._direct_rays import _segments_meet, blocker_bounds

    f = brdf.from_material(MATERIALS[0])
    sep = brdf.separable(f, K=1)
    points, normals, wo, meshes, poses, lights = _tier_scene()
    wall = builtin_mesh("plane", size=[4.2, 2.0], resolution=[4, 2])
    caster = RayCaster([wall, *meshes], transforms=[
        Transform(translate=np.array([0.0, 1.0, -1.2]), rotate_deg=np.array([90.0, 0.0, 0.0])), *poses])
    spheres, planes = blocker_bounds(caster, [True, False, False, False, False])
    points = np.concatenate([points, [[0.5, 0.75, 0.3]]])  # one inside the box's sphere
    normals = np.concatenate([normals, [[0.0, 1.0, 0.0]]])
    wo = mirror_wo(np.concatenate([wo, [[0.0, 1.0, 0.0]]]), normals)
    for i, light in enumerate(lights[:2]):
        stats = {}
        light_terms(points, normals, wo, f, sep, caster, light, i, 64, seed=3, stats=stats,
                    blockers=(spheres, planes))
        st = (np.stack([a.ravel() for a in np.meshgrid(np.arange(8) / 8, np.arange(8) / 8, indexing="ij")],
                       axis=1)[None] + jitter(3, i, np.arange(len(points)), 64) / 8) * 2.0 - 1.0
        y = light.center + st[..., :1] * light.u + st[..., 1:] * light.v
        d = y - points[:, None]
        live = (np.einsum("vmi,vi->vm", d, normals) > 0.0) & (-(d @ light.normal) > 0.0)
        sx, sy = points @ planes[:, :3].T, y @ planes[:, :3].T  # (V, P), (V, m, P)
        slab = ~(((sx[:, None] > planes[:, 4]) & (sy > planes[:, 4])) | ((sx[:, None] < planes[:, 3])
                                                                          & (sy < planes[:, 3])))
        inside = np.any(np.sum((points[:, None] - spheres[None, :, :3]) ** 2, axis=-1) <= spheres[:, 3] ** 2, axis=1)
        meets = _segments_meet(points, y, spheres) | slab.any(axis=-1) | inside[:, None]
        assert inside[-1] and 0 < stats["rays_cast"] < live.sum()
        assert stats["rays_cast"] == np.sum(meets & live)


def test_the_guided_node_search_equals_searchsorted():
    """``_interval`` (a table starts the search) finds ``searchsorted(nodes, theta) - 1`` and its ``t`` for every
    angle: random ones, the nodes themselves and their float neighbours, the table's bin edges, the ends."""
    from prtlab.interreflection._direct_rays import _GUIDE_BINS, _guide, _interval

    sep = brdf.separable(brdf.from_material(MATERIALS[1]), K=4)
    nodes, _ = sep._ext(sep.theta_in, sep.g_radial, 0.5 * np.pi)
    guide, per_radian = _guide(nodes)
    edges = np.arange(_GUIDE_BINS + 1) / per_radian
    theta = np.concatenate([np.random.default_rng(4).uniform(-0.1, 1.7, 20_000), nodes, np.nextafter(nodes, -1.0),
                            np.nextafter(nodes, 9.0), edges, np.nextafter(edges, -1.0), np.nextafter(edges, 9.0)])
    last = len(nodes) - 1
    for th in theta:
        j, t = _interval(nodes, guide, per_radian, th)
        if th <= nodes[0]:
            assert (j, t) == (0, 0.0)
        elif th >= nodes[last]:
            assert (j, t) == (last - 1, 1.0)
        else:
            expected = np.searchsorted(nodes, th) - 1
            assert j == expected and t == (th - nodes[j]) / (nodes[j + 1] - nodes[j])


def test_the_polar_angle_is_numpys_arctan2_within_a_few_units_in_the_last_place():
    """``_polar_angle(r, z)`` (the kernel's ``theta``, a table and a series instead of libm's ``atan2``) is
    ``arctan2(r, z)`` within 1e-15 relative over the upper half-plane: random directions, the reduction points'
    ratios and their float neighbours, the axes, zero, tiny and huge components."""
    from prtlab.interreflection._direct_rays import _ATAN_POINTS, _polar_angle

    angle = np.random.default_rng(5).uniform(0.0, np.pi, 20_000)
    r, z = [np.abs(np.sin(angle))], [np.cos(angle)]
    for ratio in np.concatenate([_ATAN_POINTS, np.nextafter(_ATAN_POINTS, -1.0), np.nextafter(_ATAN_POINTS, 2.0),
                                 (_ATAN_POINTS[1:] + _ATAN_POINTS[:-1]) / 2]).clip(0.0):
        for a, b in ((ratio, 1.0), (1.0, ratio), (1.0, -ratio), (ratio, -1.0)):
            r.append([a, 1e-200 * a, 1e200 * a])
            z.append([b, 1e-200 * b, 1e200 * b])
    r.append([0.0, 0.0, 0.0, 1e-300, 1.0, 1.0, 5e-324])
    z.append([0.0, -1.0, 1.0, -1.0, 0.0, -0.0, 1.0])
    r, z = np.concatenate(r), np.concatenate(z)
    ours = np.array([_polar_angle(a, b) for a, b in zip(r, z)])
    expected = np.arctan2(r, z)
    assert np.all(np.abs(ours - expected) <= 1e-15 * np.maximum(expected, 5e-324))


def test_a_vertex_called_unlit_has_no_live_sample():
    """``_unlit`` (the kernel skips such a vertex's samples) is True only where no sample of the light is live
    (``cos_x > 0`` and ``cos_l > 0`` as the reference tier draws and computes them): random vertices and
    normals, and normals whose horizon passes through a corner of the light, tilted by tiny angles either way."""
    from prtlab.interreflection._direct_rays import _light_geometry, _unlit

    rng = np.random.default_rng(6)
    m = 64
    params, rows, side, _ = _light_geometry(LIGHT, m)
    points = rng.uniform(-3.0, 3.0, (4000, 3))
    normals = rng.normal(size=(4000, 3))
    corners = LIGHT.center + np.array([[s, t] for s in (-1, 1) for t in (-1, 1)]) @ np.stack([LIGHT.u, LIGHT.v])
    grazing = np.cross(corners[rng.integers(0, 4, 4000)] - points, rng.normal(size=(4000, 3)))  # n . (corner - x) = 0
    grazing += rng.choice([-1e-13, -1e-15, 0.0, 1e-15, 1e-13], (4000, 1)) * rng.normal(size=(4000, 3))
    points, normals = np.concatenate([points, points]), np.concatenate([normals, grazing])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    corner = np.stack([a.ravel() for a in np.meshgrid(np.arange(rows) / rows, np.arange(side) / side,
                                                       indexing="ij")], axis=1)
    st = (corner[None] + jitter(0, 0, np.arange(len(points)), m) * np.array([1.0 / rows, 1.0 / side])) * 2.0 - 1.0
    y = LIGHT.center + st[..., :1] * LIGHT.u + st[..., 1:] * LIGHT.v
    d = y - points[:, None]
    w = d / np.linalg.norm(d, axis=-1)[..., None]
    live = (np.einsum("vmi,vi->vm", w, normals) > 0.0) & (-w @ LIGHT.normal > 0.0)
    unlit = np.array([_unlit(*x, *n, params) for x, n in zip(points, normals)])
    assert not live[unlit].any()
    assert unlit.sum() > 1000 and (~live.any(axis=1) & ~unlit).sum() > 0  # it decides many, not every one


def test_a_lambertian_receiver_takes_its_level_factor_within_half_its_spread():
    """A Lambertian BRDF's fitted ``g_0`` varies only by rounding (within ``LEVEL_SPREAD``), so the kernel sums the
    lit weights times the middle of its values: within half the values' spread (relative) plus rounding of the
    reference tier, masks equal; a term beyond ``LEVEL_SPREAD`` takes the interpolating path (1e-12 as above)."""
    from prtlab.interreflection._direct_rays import LEVEL_SPREAD

    f = brdf.from_material(MATERIALS[0])
    sep = brdf.separable(f, K=1)
    _, values = sep._ext(sep.theta_in, sep.g_radial, 0.5 * np.pi)
    spread = float(np.ptp(values) / np.abs(values).max())
    assert spread <= LEVEL_SPREAD  # the level path is the one tested
    points, normals, wo, meshes, poses, lights = _tier_scene()
    caster = RayCaster(meshes, transforms=poses)
    wo = mirror_wo(wo, normals)
    tilted = dataclasses.replace(sep, g_radial=sep.g_radial * (1.0 + 1e-6 * np.linspace(0.0, 1.0,
                                                                                       sep.g_radial.shape[-1])))
    for s, bound in ((sep, 0.5 * spread + 1e-14), (tilted, 1e-12)):
        for i, light in enumerate(lights):
            S, F, blocked = light_terms(points, normals, wo, f, s, caster, light, i, 64, seed=3)
            S_ref, F_ref, blocked_ref = light_terms_reference(points, normals, wo, f, s, caster, light, i, 64, seed=3)
            np.testing.assert_array_equal(blocked, blocked_ref)
            np.testing.assert_allclose(S, S_ref, rtol=0.0, atol=bound * np.abs(S_ref).max())
            np.testing.assert_allclose(F, F_ref, rtol=0.0, atol=1e-14 * np.abs(F_ref).max())


# ------------------------------------------------------------------ exact unshadowed light (light_exact_lit)

def _quadrature_of_the_cosine(points, normals, light, k=600):
    """(V,) ``integral (n . w)+ dw`` over ``light`` by the midpoint rule on a ``k x k`` grid of the parallelogram."""
    s = (np.arange(k) + 0.5) / k * 2.0 - 1.0
    y = light.center + np.repeat(s, k)[:, None] * light.u + np.tile(s, k)[:, None] * light.v
    out = np.empty(len(points))
    for i, (x, n) in enumerate(zip(points, normals)):
        d = y - x
        dist = np.linalg.norm(d, axis=1)
        cos_x, cos_l = d @ n / dist, -(d @ light.normal) / dist
        out[i] = np.sum(np.where((cos_x > 0.0) & (cos_l > 0.0), cos_x * cos_l / dist**2, 0.0)) * light.area / k**2
    return out


def test_the_exact_lit_integral_is_the_cosines_integral_over_the_light():
    """``lit_integral`` (numpy) and the kernel's ``_lit_integral``: the closed form under a parallel rectangle's
    centre (four corner rectangles, Howell's catalogue C-11); the midpoint rule over the light at random points and
    normals (lights cut by the horizon, points behind the light: 0) within 1e-5 of the largest value; the two tiers
    within 1e-14."""
    from prtlab.interreflection._direct_rays import _light_geometry, _lit_integral, lit_integral

    h, a, b = 2.0, 0.3, 0.3  # under LIGHT's centre, facing it
    A, B = a / h, b / h
    corner = (A / np.sqrt(1 + A * A) * np.arctan(B / np.sqrt(1 + A * A))
              + B / np.sqrt(1 + B * B) * np.arctan(A / np.sqrt(1 + B * B))) / (2 * np.pi)
    below = LIGHT.center - [0.0, h, 0.0]
    np.testing.assert_allclose(lit_integral(below[None], np.array([[0.0, 1.0, 0.0]]), LIGHT), 4 * np.pi * corner,
                               rtol=1e-14)
    rng = np.random.default_rng(11)
    points = LIGHT.center + rng.uniform(-1.0, 1.0, (120, 3)) * [1.2, 1.5, 1.2] - [0.0, 0.6, 0.0]
    normals = rng.normal(size=(120, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    exact = lit_integral(points, normals, LIGHT)
    params = _light_geometry(LIGHT, 64)[0]
    kernel = np.array([_lit_integral(*x, *n, params) for x, n in zip(points, normals)])
    np.testing.assert_allclose(kernel, exact, rtol=0.0, atol=1e-14 * exact.max())
    np.testing.assert_allclose(exact, _quadrature_of_the_cosine(points, normals, LIGHT), rtol=0.0,
                               atol=1e-5 * exact.max())
    behind = (points - LIGHT.center) @ LIGHT.normal <= 0.0  # the light shines along its normal
    corners = LIGHT.center + np.array([[s, t] for s in (-1, 1) for t in (-1, 1)]) @ np.stack([LIGHT.u, LIGHT.v])
    heights = np.einsum("vci,vi->vc", corners[None] - points[:, None], normals)
    clipped = (heights.max(axis=1) > 0.0) & (heights.min(axis=1) < 0.0) & ~behind
    assert np.all(exact[behind] == 0.0) and behind.sum() > 5 and clipped.sum() > 20  # both cases are tested


def test_a_vertex_called_wholly_above_has_every_sample_live():
    """``_wholly_above`` (the kernel answers such a vertex without drawing) is True only where every sample of the
    light is live as the reference tier draws it: random vertices and normals, and normals whose horizon passes
    through a corner of the light, tilted by tiny angles either way."""
    from prtlab.interreflection._direct_rays import _light_geometry, _wholly_above

    rng = np.random.default_rng(7)
    params = _light_geometry(LIGHT, 64)[0]
    points = LIGHT.center + rng.uniform(-2.0, 2.0, (4000, 3)) - [0.0, 1.0, 0.0]
    normals = rng.normal(size=(4000, 3)) + [0.0, 2.0, 0.0]
    corners = LIGHT.center + np.array([[s, t] for s in (-1, 1) for t in (-1, 1)]) @ np.stack([LIGHT.u, LIGHT.v])
    grazing = np.cross(corners[rng.integers(0, 4, 4000)] - points, rng.normal(size=(4000, 3)))
    grazing *= np.sign(grazing[:, 1:2] + 1e-300)  # toward the light
    grazing += rng.choice([-1e-13, -1e-15, 0.0, 1e-15, 1e-13], (4000, 1)) * rng.normal(size=(4000, 3))
    points, normals = np.concatenate([points, points]), np.concatenate([normals, grazing])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    live = _live(points, normals, LIGHT, 0, seed=0)
    whole = np.array([_wholly_above(*x, *n, params) for x, n in zip(points, normals)])
    assert live[whole].all()
    assert whole.sum() > 1000 and (live.all(axis=1) & ~whole).sum() > 0  # it decides many, not every one


@pytest.mark.parametrize("material", MATERIALS, ids=["lambert", "phong"])
def test_exact_lit_points_take_the_integral_and_keep_their_masks(material):
    """``exact_lit``: the kernel equals the reference tier (masks equal; sums within half the level spread of
    ``g_k``, as the level path, and 1e-13 otherwise), with and without a probe, ``decided`` and blocker culling;
    the masks equal those without ``exact_lit``; a Lambertian point with some live sample and none blocked takes
    ``lit_integral`` times ``g_k`` and ``kd / pi`` (a caster that blocks nothing: every such point), the others
    keep their sums bit for bit; a Phong receiver is unchanged bit for bit."""
    from prtlab.interreflection._direct_rays import blocker_bounds, lit_integral

    f = brdf.from_material(material)
    sep = brdf.separable(f, K=4 if material.type == "phong" else 1)
    _, values = sep._ext(sep.theta_in, sep.g_radial, 0.5 * np.pi)
    bound = 0.5 * float(np.ptp(values) / np.abs(values).max()) + 1e-13
    points, normals, wo, meshes, poses, lights = _tier_scene()
    caster = RayCaster(meshes, transforms=poses)
    empty = RayCaster([meshes[2]], transforms=[Transform(translate=np.array([50.0, 0.0, 0.0]))])
    wo = mirror_wo(wo, normals)
    decided = (np.arange(len(points)) % 3).astype(np.int8)
    blockers = blocker_bounds(caster, [False] * len(meshes))
    for i, light in enumerate(lights):
        for probe, given, bounds in ((0, None, None), (16, None, blockers), (0, decided, blockers),
                                     (16, decided, None)):
            common = dict(seed=3, probe=probe, decided=given)
            ours = light_terms(points, normals, wo, f, sep, caster, light, i, 64, exact_lit=True, blockers=bounds,
                               **common)
            ref = light_terms_reference(points, normals, wo, f, sep, caster, light, i, 64, exact_lit=True, **common)
            estimate = light_terms(points, normals, wo, f, sep, caster, light, i, 64, blockers=bounds, **common)
            np.testing.assert_array_equal(ours[2], ref[2])
            np.testing.assert_array_equal(ours[2], estimate[2])
            np.testing.assert_allclose(ours[0], ref[0], rtol=0.0, atol=bound * np.abs(ref[0]).max())
            np.testing.assert_allclose(ours[1], ref[1], rtol=0.0, atol=1e-13 * np.abs(ref[1]).max())
            if material.type == "phong" or isinstance(light, PointLight):
                for a, b in zip(ours, estimate):
                    np.testing.assert_array_equal(a, b)
                continue
            live = _live(points, normals, light, i)
            whole = live.any(axis=1) & ~ours[2].any(axis=1) & (decided != 2 if given is not None else True)
            for a, b in zip(ours[:2], estimate[:2]):
                np.testing.assert_array_equal(a[~whole], b[~whole])
            exact = lit_integral(points[whole], normals[whole], light)
            np.testing.assert_allclose(ours[0][whole, 0], exact * values[0, 0], rtol=bound)
            assert whole.sum() > 100 and np.abs(ours[0][whole] - estimate[0][whole]).max() > 1e-4 * exact.max()
        clear = light_terms(points, normals, wo, f, sep, empty, light, i, 64, seed=3, exact_lit=True)
        if material.type != "phong" and not isinstance(light, PointLight):
            some = _live(points, normals, light, i).any(axis=1)
            exact = lit_integral(points, normals, light)
            np.testing.assert_allclose(clear[0][some, 0], exact[some] * values[0, 0], rtol=bound)
            np.testing.assert_allclose(clear[1][some], exact[some, None] * f.kd / np.pi
                                       * (np.einsum("vi,vi->v", wo, normals)[some, None] >= 0.0), rtol=1e-13)


@pytest.mark.parametrize("terms", [light_terms, light_terms_reference], ids=["kernel", "reference"])
def test_an_exact_lit_recast_after_a_move_equals_an_exact_lit_cast(terms):
    """With ``exact_lit`` on a Lambertian receiver, a partial re-cast (``visibility``, ``moved``, ``previous``) equals
    a fresh cast bit for bit, with and without a probe and ``decided``, blocker culling in the kernel."""
    from prtlab.interreflection._direct_rays import blocker_bounds

    f = brdf.from_material(MATERIALS[0])
    sep = brdf.separable(f, K=1)
    points, normals, wo, meshes, lights, before, after, spheres = _before_and_after_a_move()
    first = (np.arange(len(points)) % 3).astype(np.int8)
    second = (np.arange(len(points)) % 5 % 3).astype(np.int8)
    for i, light in enumerate(lights[:2]):
        for probe, old_given, new_given in ((0, None, None), (16, None, None), (16, first, second)):
            for a_caster, b_caster in ((before, after), (after, before)):
                common = dict(probe=probe, exact_lit=True)
                if terms is light_terms:
                    common["blockers"] = blocker_bounds(b_caster, [False] * len(meshes))
                old = terms(points, normals, wo, f, sep, a_caster, light, i, 64, decided=old_given, **common)
                fresh = terms(points, normals, wo, f, sep, b_caster, light, i, 64, decided=new_given, **common)
                partial = terms(points, normals, wo, f, sep, b_caster, light, i, 64, visibility=old[2], moved=spheres,
                                decided=new_given, decided_before=old_given, **common)
                kept = terms(points, normals, wo, f, sep, b_caster, light, i, 64, visibility=old[2], moved=spheres,
                             previous=old[:2], decided=new_given, decided_before=old_given, **common)
                for a, b, c in zip(partial, kept, fresh):
                    np.testing.assert_array_equal(a, c)
                    np.testing.assert_array_equal(b, c)


def test_the_option_light_exact_lit_is_a_bool():
    with pytest.raises(TypeError, match="light_exact_lit must be True or False"):
        InterreflectionOptions(light_exact_lit=1)
