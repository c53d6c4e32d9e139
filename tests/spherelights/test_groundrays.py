"""Tests of prtlab.spherelights._groundrays (the ground shaded against the objects' meshes by ray casting, option
``ground_shading="rays"``)."""

import copy
import dataclasses

import numpy as np
import pytest

from prtlab import sh
from prtlab.geometry import builtin_mesh
from prtlab.pipeline import FrameState
from prtlab.scene import Scene
from prtlab.spherelights import SphereLights
from prtlab.spherelights._groundrays import (MAX_SPACING, candidate_rays, contact_radiance, ground_direct_rays,
                                             ground_gather_rays, ground_light_rays, ground_ray_nodes, ground_ray_rule,
                                             mesh_blockers, sphere_hits)

WHITE = np.zeros((16, 3))
WHITE[0] = np.sqrt(4 * np.pi)  # constant radiance 1


def _ball(centre, radius=0.5, subdivisions=4):
    m = builtin_mesh(name="icosphere", radius=radius, subdivisions=subdivisions)
    return np.asarray(m.vertices) + np.asarray(centre, dtype=np.float64), np.asarray(m.faces)


def _bound(verts):
    c = verts.mean(axis=0)
    return np.append(c, 1.001 * np.linalg.norm(verts - c, axis=1).max())


# ------------------------------------------------------------------ known answers


def test_rule_integrates_the_cosine_and_a_zonal_polynomial():
    """``sum w_j = pi`` and ``sum w_j cos^k = 2 pi / (k + 2)`` (Gauss-Legendre in ``cos theta``: exact up to
    degree ``2 n - 1``)."""
    rule = ground_ray_rule(8, 4)
    assert rule.dirs.shape == (32, 3) and rule.weights.shape == (32,)
    np.testing.assert_allclose(np.linalg.norm(rule.dirs, axis=1), 1.0, atol=1e-14)
    assert np.all(rule.dirs[:, 1] > 0)
    for k in range(6):
        np.testing.assert_allclose(np.sum(rule.weights * rule.dirs[:, 1] ** k), 2 * np.pi / (k + 2), rtol=1e-13)


def test_nothing_blocked_is_the_sh_irradiance(rng):
    env = rng.normal(size=(16, 3))
    env[0] += 5.0
    pts = rng.uniform(-1, 1, size=(7, 3))
    pts[:, 1] = 0.0
    empty = mesh_blockers([], np.zeros((0, 4)))
    expect = sh.basis(np.array([[0.0, 1.0, 0.0]]), 4) @ sh.irradiance(env)
    np.testing.assert_allclose(ground_direct_rays(pts, env, empty), np.broadcast_to(expect, (7, 3)), rtol=1e-12)
    np.testing.assert_array_equal(ground_gather_rays(pts, empty, []), np.zeros((7, 3)))


@pytest.mark.parametrize("as_mesh", [True, False])
def test_ball_above_a_point_is_the_closed_form(as_mesh):
    """A ball of angular radius ``a`` straight above the point, white sky: ``E = pi (1 - sin^2 a)``; a ball of
    exit radiance 1 (mesh), gathered: ``pi sin^2 a``. As a mesh (an icosphere, slightly inside the true ball) or
    as an opaque sphere (a local light)."""
    centre = np.array([0.0, 2.0, 0.0])
    p = np.zeros((1, 3))
    rule = ground_ray_rule(128, 64)
    if as_mesh:
        v, f = _ball(centre, 0.5, 5)
        blk = mesh_blockers([(v, f)], _bound(v))
        sin2 = (np.linalg.norm(v - centre, axis=1).min() / 2.0) ** 2  # the inscribed ball's, to within the facets
    else:
        blk = mesh_blockers([], np.zeros((0, 4)), np.append(centre, 0.5))
        sin2 = 0.25**2
    e = ground_direct_rays(p, WHITE, blk, rule)
    np.testing.assert_allclose(e, np.pi * (1 - sin2), rtol=2e-3)
    if as_mesh:
        g = ground_gather_rays(p, blk, [np.ones((len(v), 3))], rule)
        np.testing.assert_allclose(g, np.pi * sin2, rtol=0.03)


def test_point_inside_a_closed_mesh_gets_nothing():
    """A ground point under a box resting on the ground (inside it once offset): no direct light, and the box's
    inner faces (back faces) give no gathered light."""
    box = builtin_mesh(name="box", size=[1.0, 1.0, 1.0])
    v = np.asarray(box.vertices) + [0.0, 0.5, 0.0]
    blk = mesh_blockers([(v, np.asarray(box.faces))], _bound(v))
    p = np.array([[0.1, 0.0, -0.2], [3.0, 0.0, 0.0]])
    e = ground_direct_rays(p, WHITE, blk)
    g = ground_gather_rays(p, blk, [np.ones((len(v), 3))])
    np.testing.assert_allclose(e[0], 0.0, atol=1e-12)
    np.testing.assert_array_equal(g[0], 0.0)
    assert np.all(e[1] > 2.5) and np.all(g[1] > 0.0)


def test_contact_radiance_keeps_the_part_above_the_ground():
    """At a ground's height: scaled by ``(1 + n_y) / 2`` (0 facing down, 1/2 sideways, 1 up); elsewhere as given."""
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 1e-9, 0.0], [2.0, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, -2.0, 0.0]])
    nrm = np.array([[0.0, -2.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.0, -1.0, 0.0]])
    rad = np.arange(15.0).reshape(5, 3) + 1.0
    out = contact_radiance(pts, nrm, rad, [0.0, 5.0], 1e-6)
    np.testing.assert_array_equal(out, rad * np.array([0.0, 0.5, 1.0, 1.0, 1.0])[:, None])
    np.testing.assert_array_equal(contact_radiance(pts, nrm, rad, [], 1e-6), rad)
    assert contact_radiance(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), [0.0], 1e-6).shape == (0, 3)


# ------------------------------------------------------------------ tiers


def test_sphere_hits_kernel_matches_reference(rng):
    pts = rng.uniform(-2, 2, size=(40, 3))
    dirs = rng.normal(size=(50, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    spheres = np.concatenate([rng.uniform(-2, 2, size=(6, 3)), rng.uniform(0.2, 1.0, size=(6, 1))], axis=1)
    fast = sphere_hits(pts, dirs, spheres)
    ref = sphere_hits(pts, dirs, spheres, method="reference")
    assert np.isinf(ref).any() and (ref == 0).any() and np.isfinite(ref[ref > 0]).any()
    np.testing.assert_array_equal(np.isinf(fast), np.isinf(ref))
    np.testing.assert_allclose(fast[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=1e-12, atol=1e-14)
    assert sphere_hits(np.zeros((0, 3)), dirs, spheres).shape == (0, 50)
    np.testing.assert_array_equal(candidate_rays(pts, dirs, spheres), np.isfinite(ref))
    np.testing.assert_array_equal(candidate_rays(pts, dirs, spheres, method="reference"), np.isfinite(ref))
    assert candidate_rays(pts, dirs, np.zeros((0, 4))).sum() == 0


def test_embree_matches_the_numpy_caster(rng):
    """The engines agree ray by ray; the sums differ only where a ray grazes an edge (float32)."""
    v, f = _ball([0.3, 0.6, -0.2], 0.5, 2)
    blk = mesh_blockers([(v, f)], _bound(v), np.array([[-1.0, 0.8, 0.0, 0.3]]))
    pts = np.stack([rng.uniform(-1.5, 1.5, 20), np.zeros(20), rng.uniform(-1.5, 1.5, 20)], axis=1)
    env = WHITE.copy()
    env[2] = 0.5
    rule = ground_ray_rule(16, 6)
    rad = [rng.uniform(0, 1, size=(len(v), 3))]
    np.testing.assert_allclose(ground_direct_rays(pts, env, blk, rule),
                               ground_direct_rays(pts, env, blk, rule, method="numpy"), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(ground_gather_rays(pts, blk, rad, rule),
                               ground_gather_rays(pts, blk, rad, rule, method="numpy"), rtol=1e-5, atol=1e-6)


def test_one_cast_gives_the_direct_and_gathered_light(rng):
    """``ground_light_rays`` is ``ground_direct_rays`` and ``ground_gather_rays`` from one closest-hit cast, in a
    turned, shifted and scaled frame (which changes nothing but rounding)."""
    v, f = _ball([0.3, 0.6, -0.2], 0.5, 2)
    pts = np.stack([rng.uniform(-1.5, 1.5, 30), np.zeros(30), rng.uniform(-1.5, 1.5, 30)], axis=1)
    env = WHITE.copy()
    env[3] = 0.4
    rad = [rng.uniform(0, 1, size=(len(v), 3))]
    rule = ground_ray_rule(16, 6)
    blk = mesh_blockers([(v, f)], _bound(v), np.array([[-1.0, 0.8, 0.0, 0.3]]))
    turned = mesh_blockers([(v, f)], _bound(v), np.array([[-1.0, 0.8, 0.0, 0.3]]), origin=[0.2, 0.0, -0.1],
                           azimuth=0.0, scale=2.5)
    direct, gathered = ground_light_rays(pts, env, blk, rad, rule)
    np.testing.assert_allclose(direct, ground_direct_rays(pts, env, blk, rule), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(gathered, ground_gather_rays(pts, blk, rad, rule), rtol=1e-12, atol=1e-12)
    d2, g2 = ground_light_rays(pts, env, turned, rad, rule)
    np.testing.assert_allclose(d2, direct, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(g2, gathered, rtol=1e-4, atol=1e-5)


def test_chunks_scheduled_by_their_rays_give_the_same_light(rng, monkeypatch):
    """Two numba threads, 1,200 points near a ball (5 chunks, most rays in the nearest): the direct and gathered
    light (one closest-hit cast) and the direct light alone (any-hit rays), with the chunks' ``sizes`` given to
    ``run_tasks`` (the largest first on every thread) and without, bit for bit."""
    from prtlab import _tasks
    from prtlab.spherelights import _groundrays
    from tests.conftest import two_numba_threads

    two_numba_threads()
    v, f = _ball([0.3, 0.6, -0.2], 0.5, 3)
    pts = np.stack([rng.uniform(-3, 3, 1200), np.zeros(1200), rng.uniform(-3, 3, 1200)], axis=1)
    pts = pts[np.argsort(np.hypot(pts[:, 0] - 0.3, pts[:, 2] + 0.2))]  # the nearest first: one heavy chunk
    rad = [rng.uniform(0, 1, size=(len(v), 3))]
    blk = mesh_blockers([(v, f)], _bound(v), np.array([[-1.0, 0.8, 0.0, 0.3]]))
    env = WHITE.copy()
    env[3] = 0.4
    sizes = _groundrays._chunk_sizes(pts, blk, len(ground_ray_rule().dirs))
    assert len(sizes) == 5 and sizes[0] > sum(sizes) / 2
    scheduled = (*ground_light_rays(pts, env, blk, rad), ground_direct_rays(pts, env, blk))
    monkeypatch.setattr(_groundrays, "run_tasks", lambda jobs, sizes=None: _tasks.run_tasks(jobs))
    for a, b in zip(scheduled, (*ground_light_rays(pts, env, blk, rad), ground_direct_rays(pts, env, blk))):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("opaque", [False, True])
def test_hit_sums_kernel_matches_reference(seed, opaque):
    """The numba tier of the sums over the hits is the numpy specification's (the same sums in the same order):
    two meshes (one a back face seen from inside), points under and beside them, with and without an opaque
    sphere in front of some hits."""
    rng = np.random.default_rng(seed)
    v1, f1 = _ball(rng.uniform([-0.5, 0.4, -0.5], [0.5, 0.8, 0.5]), rng.uniform(0.3, 0.5), 2)
    v2, f2 = _ball([1.2, 0.3, 0.2], 0.3, 1)
    bounds = np.stack([_bound(v1), _bound(v2), [0.0, 0.0, 0.0, 0.2]])  # the last bound holds no mesh
    spheres = np.array([[-0.8, 1.2, 0.1, 0.35]]) if opaque else ()
    blk = mesh_blockers([(v1, f1), (v2, f2)], bounds, spheres, origin=[0.1, 0.0, -0.2], azimuth=0.4, scale=1.7)
    pts = np.stack([rng.uniform(-1.5, 1.5, 40), np.zeros(40), rng.uniform(-1.5, 1.5, 40)], axis=1)
    pts[0] = [1.2, 0.3, 0.2]  # inside the second ball: back faces only
    env = rng.normal(size=(16, 3))
    env[0] += 4.0
    rad = [rng.uniform(0, 1, size=(len(v1), 3)), rng.uniform(0, 2, size=(len(v2), 3))]
    rule = ground_ray_rule(24, 6)
    fast = ground_light_rays(pts, env, blk, rad, rule)
    ref = ground_light_rays(pts, env, blk, rad, rule, tier="reference")
    for a, b in zip(fast, ref):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-14)
    assert np.abs(ref[1]).max() > 0.01  # some light was gathered
    np.testing.assert_allclose(ground_gather_rays(pts, blk, rad, rule),
                               ground_gather_rays(pts, blk, rad, rule, tier="reference"), rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("rule", [(64, 16), (32, 8), (7, 3)])
def test_candidate_rays_on_rings_match_the_direction_by_direction_test(rng, rule):
    """On a product rule the kernel tests only the azimuth windows of the cones that meet a ring: the same
    result as testing every direction against every sphere (spheres below, above and around the points, some
    points inside one), and as the float64 reference but for rays grazing a cone."""
    from prtlab.spherelights._groundrays import _candidates, _candidates_kernel, _rings

    dirs = ground_ray_rule(*rule).dirs
    assert _rings(dirs) == rule[0] and _rings(dirs[::-1].copy()) == 0
    for _ in range(5):
        pts = np.stack([rng.uniform(-2, 2, 200), rng.uniform(-0.1, 0.3, 200), rng.uniform(-2, 2, 200)], axis=1)
        spheres = np.concatenate([rng.uniform([-2, -0.5, -2], [2, 2, 2], (9, 3)), rng.uniform(0.05, 0.8, (9, 1))],
                                 axis=1)
        fast = candidate_rays(pts, dirs, spheres)
        each = np.empty_like(fast)
        _candidates_kernel(pts, np.ascontiguousarray(dirs), spheres, each, np.empty(0, dtype=np.int64))
        np.testing.assert_array_equal(fast, each)
        for n_azimuth in (_rings(dirs), 0):  # the counts of both kernels
            counts = np.full(len(pts), -1, dtype=np.int64)
            _candidates(pts, np.ascontiguousarray(dirs), spheres, n_azimuth, counts)
            np.testing.assert_array_equal(counts, fast.sum(axis=1))
        assert (fast != candidate_rays(pts, dirs, spheres, method="reference")).mean() < 1e-4
        assert 0.05 < fast.mean() < 0.95


def test_ray_lists_are_the_nonzero_candidates(rng):
    """``_list_rays``: the candidate rays point by point in the order of ``np.nonzero``, with their origins and
    directions (rows without a candidate, all candidates, none at all)."""
    from prtlab.spherelights._groundrays import _list_rays

    for density in (0.0, 0.2, 1.0):
        cand = rng.uniform(size=(13, 40)) < density
        cand[3] = False
        pts, dirs = rng.normal(size=(13, 3)), rng.normal(size=(40, 3))
        ptr = np.concatenate([[0], np.cumsum(cand.sum(axis=1))])
        ip, ik = np.empty(ptr[-1], dtype=np.int64), np.empty(ptr[-1], dtype=np.int64)
        origins, ray_dirs = np.empty((ptr[-1], 3)), np.empty((ptr[-1], 3))
        _list_rays(pts, cand, dirs, ptr, 0.0, ip, ik, origins, ray_dirs)
        ref_p, ref_k = np.nonzero(cand)
        np.testing.assert_array_equal(ip, ref_p)
        np.testing.assert_array_equal(ik, ref_k)
        np.testing.assert_array_equal(origins, pts[ref_p])
        np.testing.assert_array_equal(ray_dirs, dirs[ref_k])
        _list_rays(pts, cand, dirs, ptr, 1e-4, ip, ik, origins, ray_dirs)  # offset as the caster's normals do
        side = np.where(dirs[ref_k, 1] >= 0.0, 1e-4, -1e-4)
        np.testing.assert_array_equal(origins, pts[ref_p] + side[:, None] * np.array([0.0, 1.0, 0.0]))


def test_candidate_rays_leave_out_nothing_that_hits(rng):
    """Only rays meeting a bounding sphere are cast: the result equals casting every ray (a bound as large as
    the scene)."""
    v, f = _ball([0.0, 0.5, 0.0], 0.5, 2)
    pts = np.stack([rng.uniform(-1, 1, 15), np.zeros(15), rng.uniform(-1, 1, 15)], axis=1)
    tight = mesh_blockers([(v, f)], _bound(v))
    loose = mesh_blockers([(v, f)], np.array([0.0, 0.0, 0.0, 100.0]))
    rule = ground_ray_rule(16, 6)
    np.testing.assert_array_equal(ground_direct_rays(pts, WHITE, tight, rule),
                                  ground_direct_rays(pts, WHITE, loose, rule))


# ------------------------------------------------------------------ rays at a subset of the points (``spacing``)


def _ground_points(rng, n, height=0.0, half=3.0):
    return np.stack([rng.uniform(-half, half, n), np.full(n, height), rng.uniform(-half, half, n)], axis=1)


_SPHERES = np.array([[0.0, 0.5, 0.0, 0.5], [1.6, 0.3, -0.4, 0.3], [-1.5, 1.2, 1.0, 0.4]])


@pytest.mark.parametrize("spacing", [0.2, 0.5, MAX_SPACING])
def test_nodes_interpolate_an_affine_field_exactly(rng, spacing):
    """Bilinear weights sum to 1 and reproduce an affine function of the plane; the cast rows are the points
    cast at themselves (in order) then the grid's nodes at the points' height."""
    pts = _ground_points(rng, 3000, height=0.25)
    cast, rows, weights = ground_ray_nodes(pts, _SPHERES, spacing)
    assert len(cast) < len(pts) and rows.shape == weights.shape == (len(pts), 4)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-14)
    assert weights.min() >= 0.0 and np.all(cast[:, 1] == 0.25)
    field = np.stack([1.0 + 2.0 * cast[:, 0] - 0.5 * cast[:, 2], cast[:, 0] * 0.0 + 3.0, -cast[:, 2]], axis=1)
    value = np.einsum("pc,pci->pi", weights, field[rows])
    np.testing.assert_allclose(value, np.stack([1.0 + 2.0 * pts[:, 0] - 0.5 * pts[:, 2], np.full(len(pts), 3.0),
                                                -pts[:, 2]], axis=1), atol=1e-12)
    own = weights[:, 0] == 1.0
    n_own = own.sum()
    np.testing.assert_array_equal(cast[:n_own], pts[own])
    np.testing.assert_array_equal(rows[own], np.repeat(np.arange(n_own)[:, None], 4, axis=1))
    assert np.all(rows[~own] >= n_own)


@pytest.mark.parametrize("spacing", [0.2, 0.5, MAX_SPACING])
def test_nodes_keep_the_points_near_the_spheres(rng, spacing):
    """A point takes its cell's corners only if the cell's side is at most ``spacing`` times its gap to the
    nearest sphere (so every corner lies outside the spheres); the points nearest the spheres are cast."""
    pts = _ground_points(rng, 3000)
    cast, rows, weights = ground_ray_nodes(pts, _SPHERES, spacing)
    gap = np.min(np.linalg.norm(pts[:, None] - _SPHERES[None, :, :3], axis=2) - _SPHERES[:, 3], axis=1)
    far = weights[:, 0] < 1.0
    corners = cast[rows[far]]  # (I, 4, 3)
    side = np.abs(corners[:, 3, [0, 2]] - corners[:, 0, [0, 2]])
    np.testing.assert_allclose(side[:, 0], side[:, 1], rtol=1e-12)
    assert np.all(side[:, 0] <= spacing * gap[far] * (1 + 1e-12))
    assert np.all(np.abs(pts[far][:, None, [0, 2]] - corners[:, :, [0, 2]]) <= side[:, None, :] * (1 + 1e-12))
    corner_gap = np.min(np.linalg.norm(corners[:, :, None] - _SPHERES[None, None, :, :3], axis=3)
                        - _SPHERES[:, 3], axis=2)
    assert corner_gap.min() > 0.0
    assert np.all(~far[np.argsort(gap)[:100]])  # the nearest points are cast at themselves
    assert far.sum() > 0.5 * len(pts) if spacing >= 0.5 else far.any()


def test_gaps_kernel_matches_numpy(rng):
    """``_gaps`` (the distance to the nearest sphere's surface in ``ground_ray_nodes``): bitwise the numpy
    expression it replaced, points inside spheres included."""
    from prtlab.spherelights._groundrays import _gaps

    pts = rng.normal(size=(3000, 3)) * 2.0
    sph = np.concatenate([rng.normal(size=(14, 3)), rng.uniform(0.1, 1.0, (14, 1))], axis=1)
    expected = np.min(np.sqrt(sum((pts[:, i, None] - sph[None, :, i]) ** 2 for i in range(3))) - sph[None, :, 3],
                      axis=1)
    out = np.empty(len(pts))
    _gaps(pts, sph, out)
    np.testing.assert_array_equal(out, expected)
    assert (out < 0).any()


def test_nodes_cast_at_every_point_when_they_cannot_help(rng):
    """Spacing 0, no spheres, a handful of points, points at several heights, or a grid that would need as many
    casts as there are points: every point cast at itself."""
    pts = _ground_points(rng, 500)
    for args in [(pts, _SPHERES, 0.0), (pts, np.zeros((0, 4)), 0.5), (pts[:5], _SPHERES, 0.5),
                 (pts + np.arange(500)[:, None] * [0.0, 1e-3, 0.0], _SPHERES, 0.5),
                 (pts[:40], _SPHERES, 0.5), (np.zeros((0, 3)), _SPHERES, 0.5)]:
        cast, rows, weights = ground_ray_nodes(*args)
        np.testing.assert_array_equal(cast, args[0])
        np.testing.assert_array_equal(rows, np.repeat(np.arange(len(args[0]))[:, None], 4, axis=1))
        np.testing.assert_array_equal(weights, np.tile([1.0, 0.0, 0.0, 0.0], (len(args[0]), 1)))


def test_nodes_turn_with_the_scene(rng):
    """The grid follows the points' box, so a similarity of the plane (scale, shift) picks the same casts."""
    pts = _ground_points(rng, 2000)
    cast, rows, weights = ground_ray_nodes(pts, _SPHERES, 0.5)
    shift, scale = np.array([0.7, 0.0, -0.3]), 2.5
    sph = np.concatenate([(_SPHERES[:, :3] + shift) * scale, _SPHERES[:, 3:] * scale], axis=1)
    cast2, rows2, weights2 = ground_ray_nodes((pts + shift) * scale, sph, 0.5)
    np.testing.assert_array_equal(rows2, rows)
    np.testing.assert_allclose(weights2, weights, atol=1e-9)
    np.testing.assert_allclose(cast2, (cast + shift) * scale, atol=1e-12)


def _spacing_scene(rng):
    """A ball resting on the ground, a box beside it, an opaque sphere (a local light) above; 1,500 ground points."""
    v, f = _ball([0.0, 0.5, 0.0], 0.5, 3)
    box = builtin_mesh(name="box", size=[0.6, 0.6, 0.6])
    bv = np.asarray(box.vertices) + [1.4, 0.3, -0.5]
    bounds = np.stack([_bound(v), _bound(bv)])
    blk = mesh_blockers([(v, f), (bv, np.asarray(box.faces))], bounds, np.array([[-1.2, 1.5, 0.8, 0.3]]),
                        origin=[0.1, 0.0, 0.2], azimuth=0.3, scale=3.0)
    env = WHITE.copy()
    env[2] = 0.6
    env[3] = 0.2
    rad = [rng.uniform(0.2, 1.0, size=(len(v), 3)), rng.uniform(0.2, 1.0, size=(len(bv), 3))]
    return _ground_points(rng, 1500), env, blk, rad


def test_spacing_casts_the_near_points_as_before(rng):
    """The points cast at themselves get the values of ``spacing=0`` bit for bit; ``spacing=0`` is the default."""
    pts, env, blk, rad = _spacing_scene(rng)
    rule = ground_ray_rule(32, 8)
    exact = ground_light_rays(pts, env, blk, rad, rule)
    for a, b in zip(exact, ground_light_rays(pts, env, blk, rad, rule, spacing=0.0)):
        np.testing.assert_array_equal(a, b)
    local = (pts - blk.origin) @ blk.turn / blk.scale
    _, _, weights = ground_ray_nodes(local, np.concatenate([blk.bounds, blk.spheres]), 0.5)
    own = weights[:, 0] == 1.0
    assert 0 < own.sum() < 0.5 * len(pts)
    for a, b in zip(exact, ground_light_rays(pts, env, blk, rad, rule, spacing=0.5)):
        np.testing.assert_array_equal(b[own], a[own])
    np.testing.assert_array_equal(ground_direct_rays(pts, env, blk, rule, spacing=0.5)[own],
                                  ground_direct_rays(pts, env, blk, rule)[own])


def test_spacing_stays_within_the_rules_error(rng):
    """Against a fine rule (256 x 64 rays, the truth here) the interpolated light at ``spacing=0.5`` is within
    1.25 times the per-point 64 x 16 rule's own error (relative RMS over the points, direct and gathered; measured
    1.00 and 1.04), and within 0.5 % (direct) and 3 % (gathered) of the per-point rule (measured 0.22 % and
    1.3 %)."""
    pts, env, blk, rad = _spacing_scene(rng)
    rule = ground_ray_rule(64, 16)
    sub = rng.choice(len(pts), 200, replace=False)
    fine = ground_light_rays(pts[sub], env, blk, rad, ground_ray_rule(256, 64))
    exact = ground_light_rays(pts, env, blk, rad, rule)
    coarse = ground_light_rays(pts, env, blk, rad, rule, spacing=0.5)

    def rel(x, y):
        return np.sqrt(np.mean((x - y) ** 2)) / np.sqrt(np.mean(y**2))

    for part in range(2):
        assert rel(coarse[part][sub], fine[part]) <= 1.25 * rel(exact[part][sub], fine[part]), part
        assert rel(coarse[part], exact[part]) <= (0.005, 0.03)[part], part


def test_spacing_errors():
    with pytest.raises(ValueError, match="spacing"):
        ground_ray_nodes(np.zeros((10, 3)), _SPHERES, MAX_SPACING + 0.1)
    with pytest.raises(ValueError, match="spacing"):
        ground_ray_nodes(np.zeros((10, 3)), _SPHERES, -0.1)
    with pytest.raises(TypeError, match="spacing"):
        ground_ray_nodes(np.zeros((10, 3)), _SPHERES, "0.5")
    with pytest.raises(ValueError, match="option ground_ray_spacing"):
        SphereLights.precompute(_scene(), {"ground_ray_spacing": 0.9, "n_spheres": 1}, cache=False, progress=False)


# ------------------------------------------------------------------ the pipeline


def _scene():
    return Scene.from_dict({"objects": [
        {"name": "plane", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [8, 8]},
         "material": {"type": "diffuse", "albedo": [0.7] * 3}},
        {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 2},
         "transform": {"translate": [0.0, 0.5, 0.0]}, "material": {"type": "diffuse", "albedo": [0.8] * 3},
         "dynamic": True}],
        "lights": [{"type": "environment", "constant": [1, 1, 1]}]})


@pytest.fixture(scope="module")
def ball_on_plane():
    sc = _scene()
    return sc, SphereLights.precompute(sc, {"n_spheres": 1, "fit_resolution": 12}, cache=False, progress=False)


def test_pipeline_ground_shading(ball_on_plane):
    """``"rays"`` changes the ground's rows only (and the objects' indirect light, through the ground's texture);
    the ground under the ball's contact point is dark, far from it lit by the open sky."""
    sc, pre = ball_on_plane
    st = FrameState.from_scene(sc)
    rays = pre.shade(st)
    other = copy.copy(pre)
    other.options = dataclasses.replace(pre.options, ground_shading="lights")
    lights = other.shade(st)
    assert rays.info["ground_shading"] == "rays" and lights.info["ground_shading"] == "lights"
    np.testing.assert_array_equal(rays.direct["ball"], lights.direct["ball"])
    plane = sc.object("plane")
    pts = plane.world_shading_points(plane.transform)
    centre = np.argmin(np.linalg.norm(pts[:, [0, 2]], axis=1))
    far = np.argmax(np.linalg.norm(pts[:, [0, 2]], axis=1))
    assert rays.direct["plane"][centre].max() < 0.05 * rays.direct["plane"][far].min()
    assert np.all(rays.indirect["plane"] >= 0) and rays.indirect["plane"][far].max() < rays.indirect["plane"].max()
    np.testing.assert_allclose(rays.total["plane"], rays.direct["plane"] + rays.indirect["plane"])


def test_pipeline_ground_ray_spacing():
    """``ground_ray_spacing`` casts the ground's rays at fewer places (its vertices and texels) and changes the
    ground's light within the rule's own error; the ball's direct light is not the ground's rays'."""
    sc = _scene()
    plane = sc.object("plane")
    plane.mesh = builtin_mesh(name="plane", size=[4, 4], resolution=[40, 40])
    pre = SphereLights.precompute(sc, {"n_spheres": 1, "fit_resolution": 12}, cache=False, progress=False)
    st = FrameState.from_scene(sc)
    assert pre.options.ground_ray_spacing == 0.5
    fewer = pre.shade(st)
    other = copy.copy(pre)
    other.options = dataclasses.replace(pre.options, ground_ray_spacing=0.0)
    every = other.shade(st)
    np.testing.assert_array_equal(fewer.direct["ball"], every.direct["ball"])
    for part, tol in (("direct", 0.01), ("indirect", 0.05)):
        a, b = getattr(every, part)["plane"], getattr(fewer, part)["plane"]
        assert 0.0 < np.sqrt(np.mean((a - b) ** 2)) < tol * np.sqrt(np.mean(a**2)), part
    np.testing.assert_allclose(fewer.indirect["ball"], every.indirect["ball"], rtol=0.01)


def test_ground_shading_option_errors():
    with pytest.raises(ValueError, match="option ground_shading"):
        SphereLights.precompute(_scene(), {"ground_shading": "mesh", "n_spheres": 1}, cache=False, progress=False)


def test_gather_errors():
    v, f = _ball([0.0, 1.0, 0.0])
    blk = mesh_blockers([(v, f)], _bound(v))
    with pytest.raises(ValueError, match="radiance must give one"):
        ground_gather_rays(np.zeros((1, 3)), blk, [])
    with pytest.raises(ValueError, match="method"):
        sphere_hits(np.zeros((1, 3)), np.ones((1, 3)), np.ones((1, 4)), method="fast")
    with pytest.raises(ValueError, match="tier"):
        ground_light_rays(np.zeros((1, 3)), WHITE, blk, [np.zeros((len(v), 3))], tier="fast")
    with pytest.raises(ValueError, match="tier"):
        ground_gather_rays(np.zeros((1, 3)), blk, [np.zeros((len(v), 3))], tier="fast")
    with pytest.raises(ValueError, match="method"):
        candidate_rays(np.zeros((1, 3)), np.ones((1, 3)), np.ones((1, 4)), method="fast")


def test_interpolation_kernel_is_the_numpy_sum(rng):
    """``_interpolated`` (the kernel) gives ``_interpolated_reference``'s bits: four weighted values per point,
    summed in order."""
    from prtlab.spherelights._groundrays import _interpolated, _interpolated_reference

    values = rng.normal(size=(50, 3)) * 10.0 ** rng.integers(-3, 4, size=(50, 1))
    rows = rng.integers(0, 50, size=(400, 4))
    weights = rng.uniform(-0.2, 1.0, size=(400, 4))
    ours, ref = _interpolated(values, rows, weights), _interpolated_reference(values, rows, weights)
    assert ours.shape == (400, 3) and np.array_equal(ours.view(np.int64), ref.view(np.int64))
