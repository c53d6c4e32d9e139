"""Tests of prtlab/interreflection/_residual.py: the residual gather (issue 18) against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from prtlab import brdf
from prtlab.geometry import RayCaster, builtin_mesh
from prtlab.interreflection import InterreflectionOptions
from prtlab.interreflection._residual import cosine_directions, gather_residual, residual_hits

LAMBERT = brdf.separable(brdf.lambert([0.5, 0.5, 0.5]), 1)


def _square_form_factor(a: float, h: float) -> float:
    """Point-to-parallel-square form factor, the point ``h`` above the centre of a square of half-side ``a``:
    four corner rectangles ``(1 / 2 pi) [X / sqrt(1 + X^2) atan(Y / sqrt(1 + X^2)) + (X <-> Y)]``, X = Y = a/h."""
    x = a / h
    s = np.sqrt(1.0 + x * x)
    return 4.0 * (2.0 * x / s * np.arctan(x / s)) / (2.0 * np.pi)


def test_cosine_directions_are_cosine_weighted():
    """Unit, in the hemisphere, and E[cos] = 2/3 under the density cos / pi (closed form)."""
    normals = np.array([[0.0, 1.0, 0.0], [0.6, 0.0, 0.8]])
    d = cosine_directions(normals, 1024)
    assert d.shape == (2, 1024, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    cos = np.einsum("vni,vi->vn", d, normals)
    assert np.all(cos >= 0)
    np.testing.assert_allclose(cos.mean(axis=1), 2.0 / 3.0, atol=0.005)  # stratified: well under 1/sqrt(n)


@pytest.mark.parametrize("full", [0.0, 0.5])
@pytest.mark.parametrize("h", [0.05, 0.5, 2.0, 5.0])
def test_gather_of_a_constant_residual_is_the_form_factor(h, full):
    """A square source of constant residual ``r`` (Lambertian, ``h_k = 1``) under a point facing it:
    ``L = r F`` with F the point-to-square form factor: near (h = 0.05, 0.5: the point inside the source's
    bounding sphere, hemisphere rays) and far (h = 2, 5: rays in the sphere's cone); with ``full = 0.5`` the far
    points cast fewer rays (h = 5: 2,070 of 4,096), each weighted by their number."""
    a = 1.0
    plane = builtin_mesh("plane", size=[2 * a, 2 * a], resolution=[8, 8])
    caster = RayCaster([plane])
    point, normal = np.array([[0.0, h, 0.0]]), np.array([[0.0, -1.0, 0.0]])
    sources = {0: (np.asarray(plane.faces), np.asarray(plane.vertex_normals), LAMBERT, np.zeros(3), np.sqrt(2.0))}
    hits = residual_hits(point, normal, LAMBERT, caster, sources, 4096, full=full)
    residual = np.full((len(plane.vertices), 1, 3), 0.3)
    light = gather_residual(hits[0], residual, 1)
    # Lambert: g = 1 / pi, so L = (1 / pi) r int cos = r F
    np.testing.assert_allclose(light[0, 0], 0.3 * _square_form_factor(a, h), rtol=0.02)


def test_few_rays_of_a_per_point_grid_are_unbiased(monkeypatch):
    """A point 5 above the square (its bounding cone 0.257 sr) with ``full = 4`` casts 256 of 4,096 rays (counted with
    the source's box left out: every ray of the grid is cast); over 32 seeds the gathered constant residual's mean is
    the form factor within MC_SIGMAS standard errors."""
    from prtlab.interreflection import _residual
    from tests.conftest import MC_SIGMAS

    monkeypatch.setattr(_residual, "_points_box", lambda points: _residual.NO_BOX.reshape(2, 3))
    plane = builtin_mesh("plane", size=[2.0, 2.0], resolution=[8, 8])
    caster = RayCaster([plane])
    point, normal = np.array([[0.0, 5.0, 0.0]]), np.array([[0.0, -1.0, 0.0]])
    sources = {0: (np.asarray(plane.faces), np.asarray(plane.vertex_normals), LAMBERT, np.zeros(3), np.sqrt(2.0))}
    values = []
    for seed in range(32):
        stats = {}
        hits = residual_hits(point, normal, LAMBERT, caster, sources, 4096, seed=seed, full=4.0, stats=stats)
        assert stats["rays_cast"] == 256  # ceil(4096 0.257 / 4) = 264 rays: a 16 x 16 grid
        values.append(gather_residual(hits[0], np.ones((len(plane.vertices), 1, 1)), 1)[0, 0, 0])
    values = np.array(values)
    assert abs(values.mean() - _square_form_factor(1.0, 5.0)) <= MC_SIGMAS * values.std(ddof=1) / np.sqrt(32)


def test_the_back_of_a_source_sends_nothing():
    """A point below the plane (which faces +y) sees its back: no hits are kept."""
    plane = builtin_mesh("plane", size=[2, 2], resolution=[2, 2])
    sources = {0: (np.asarray(plane.faces), np.asarray(plane.vertex_normals), LAMBERT, np.zeros(3), np.sqrt(2.0))}
    hits = residual_hits(np.array([[0.0, -0.5, 0.0]]), np.array([[0.0, 1.0, 0.0]]), LAMBERT, RayCaster([plane]),
                         sources, 64)
    assert hits == {}


def test_residual_rays_is_validated():
    with pytest.raises(ValueError, match="residual_rays"):
        InterreflectionOptions(residual_rays=-1)
    with pytest.raises(ValueError, match="residual_cone"):
        InterreflectionOptions(residual_cone=-0.5)
    with pytest.raises(ValueError, match="full"):
        residual_hits(np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]]), LAMBERT, RayCaster([builtin_mesh("plane")]), {},
                      16, full=-1.0)


def test_per_point_grids_cast_fewer_rays_toward_small_sources():
    """With ``full``, points that see a source small cast fewer rays (at least ``MIN_RAYS``), points that see it
    large all of them: the floor's rays toward the ball drop, and every kept hit is one of the ray ids its
    point's grid has."""
    from prtlab.interreflection._residual import MIN_RAYS

    meshes, poses, _ = _objects()
    caster = RayCaster(meshes, transforms=poses)
    x, n = _receiver(meshes, poses, 0)
    srcs = _sources(meshes, poses, [1], (LAMBERT, LAMBERT, LAMBERT))
    counts = {}
    for full in (0.0, 0.5):
        stats = {}
        hits = residual_hits(x, n, LAMBERT, caster, srcs, 64, full=full, stats=stats)
        counts[full] = stats["rays_cast"]
        per_point = np.bincount(hits[1].rows, minlength=len(x))
        assert per_point.max() <= 64
    assert MIN_RAYS * len(x) <= counts[0.5] < 0.5 * counts[0.0]


# ------------------------------------------------------------------ the fast gather and the incremental cast

PHONG = brdf.separable(brdf.phong([0.4, 0.4, 0.4], [0.3, 0.3, 0.3], 20.0), 3)


def _objects():
    """A floor, a ball and a box (object space) and the box's poses: in place, moved (translated and rotated)
    far from the ball, moved against the ball."""
    from prtlab.scene import Transform

    floor = builtin_mesh("plane", size=[3.0, 3.0], resolution=[6, 6])
    ball = builtin_mesh("icosphere", radius=0.4, subdivisions=2)
    box = builtin_mesh("box", size=[0.4, 0.4, 0.4], subdivisions=1)
    poses = [Transform(), Transform(translate=np.array([0.0, 0.5, 0.0])),
             Transform(translate=np.array([0.9, 0.25, 0.6]), rotate_deg=np.array([0.0, 20.0, 0.0]))]
    moves = {"translated and rotated": Transform(translate=np.array([-0.8, 0.3, -0.7]),
                                                 rotate_deg=np.array([10.0, 65.0, 0.0])),
             "next to the ball": Transform(translate=np.array([0.62, 0.25, 0.05]),
                                           rotate_deg=np.array([0.0, 35.0, 0.0]))}
    return [floor, ball, box], poses, moves


def _sources(meshes, poses, indices, seps):
    out = {}
    for i in indices:
        T = poses[i]
        world = T.apply_points(np.asarray(meshes[i].vertices, float))
        centre = 0.5 * (world.min(axis=0) + world.max(axis=0))
        normals = np.asarray(meshes[i].vertex_normals, float) @ T.rotation.T
        out[i] = (np.asarray(meshes[i].faces), normals, seps[i], centre,
                  float(np.max(np.linalg.norm(world - centre, axis=1))))
    return out


def _receiver(meshes, poses, r):
    T = poses[r]
    n = np.asarray(meshes[r].vertex_normals, float) @ T.rotation.T
    return T.apply_points(np.asarray(meshes[r].vertices, float)) + 1e-4 * n, n


def _sphere(caster, source):
    centre = np.asarray(source[3], float)
    return np.array([*centre, np.max(np.linalg.norm(caster.world_vertices(2) - centre, axis=1))])


@pytest.mark.parametrize("seps", [(LAMBERT, LAMBERT, LAMBERT), (LAMBERT, PHONG, PHONG)])
def test_gather_operator_equals_the_reference_gather(seps):
    """The compact gather applied to a random residual equals the float64 sum over the hits, for K' = K = 1 and
    for glossy K' = K = 3."""
    from prtlab.interreflection._residual import apply_gather, gather_operator

    meshes, poses, _ = _objects()
    caster = RayCaster(meshes, transforms=poses)
    rng = np.random.default_rng(3)
    for r in (0, 1):
        x, n = _receiver(meshes, poses, r)
        srcs = _sources(meshes, poses, [i for i in range(3) if i != r], seps)
        hits = residual_hits(x, n, seps[r], caster, srcs, 64)
        assert set(hits) == set(srcs)
        for i, h in hits.items():
            residual = rng.normal(size=(len(meshes[i].vertices), seps[i].K, 3))
            ref = gather_residual(h, residual, len(x))
            op = gather_operator(h, len(x))
            assert op.uv.dtype == np.float32  # Embree's barycentrics, held exactly
            fast = apply_gather(op, residual, np.zeros_like(ref))
            at_hit = np.einsum("hv,hvkc->hkc", np.abs(h.bary), np.abs(residual)[h.vertices])
            scale = np.zeros_like(ref)
            np.add.at(scale, h.rows, np.einsum("hqk,hkc->hqc", np.abs(h.factor), at_hit))
            assert np.all(np.abs(fast - ref) <= 1e-12 * scale + 1e-300)


def test_gather_of_nothing_is_zero():
    """A receiver with no hits gets an empty operator; applying it adds nothing."""
    from prtlab.interreflection._residual import ResidualHits, apply_gather, gather_operator

    empty = ResidualHits(np.zeros(0, np.int64), np.zeros((0, 1, 1)), np.zeros(0, np.int64), np.zeros(0, np.int64),
                         np.zeros((0, 2)), np.zeros((2, 3), np.int64))
    op = gather_operator(empty, 4)
    out = apply_gather(op, np.ones((5, 1, 3)), np.zeros((4, 1, 3)))
    np.testing.assert_array_equal(out, 0.0)


@pytest.mark.parametrize("full", [0.0, 0.3])
@pytest.mark.parametrize("move", ["translated and rotated", "next to the ball"])
@pytest.mark.parametrize("r", [0, 1])
def test_incremental_cast_equals_a_full_cast(move, r, full):
    """After the box moves, casting only the rays it may block or unblock gives the hits of a full cast with
    the same seed (the same arrays), so the gathered light agrees to 1e-12, and fewer rays are cast (with and
    without per-point grids, ``full``)."""
    meshes, poses, moves = _objects()
    seps = (LAMBERT, PHONG, LAMBERT)
    before = RayCaster(meshes, transforms=poses)
    after_poses = [poses[0], poses[1], moves[move]]
    after = RayCaster(meshes, transforms=after_poses)
    assert (before.epsilon, before.tnear) == (after.epsilon, after.tnear)  # the precondition of `previous`
    x, n = _receiver(meshes, poses, r)
    src_before = _sources(meshes, poses, [i for i in range(3) if i != r], seps)
    src_after = _sources(meshes, after_poses, [i for i in range(3) if i != r], seps)
    old = residual_hits(x, n, seps[r], before, src_before, 64, seed=5, full=full)
    moved = {2: np.stack([_sphere(before, src_before[2]), _sphere(after, src_after[2])])}
    full_stats, inc_stats = {}, {}
    whole = residual_hits(x, n, seps[r], after, src_after, 64, seed=5, stats=full_stats, full=full)
    inc = residual_hits(x, n, seps[r], after, src_after, 64, seed=5, previous=old, moved=moved, stats=inc_stats,
                        full=full)
    assert set(inc) == set(whole)
    rng = np.random.default_rng(1)
    for i in whole:
        for a, b in zip(whole[i].arrays(), inc[i].arrays()):
            np.testing.assert_array_equal(a, b)
        residual = rng.normal(size=(len(meshes[i].vertices), seps[i].K, 3))
        ref = gather_residual(whole[i], residual, len(x))
        np.testing.assert_allclose(gather_residual(inc[i], residual, len(x)), ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    assert inc_stats["rays_cast"] < full_stats["rays_cast"]


@pytest.mark.parametrize("full", [0.0, 0.3])
def test_rays_depend_on_the_point_and_source_alone(full):
    """A ray is a function of (seed, source, point, ray index): the rays of a subset of the points are those
    of the whole set (what the incremental cast relies on), with and without per-point grids (``full``)."""
    from prtlab.interreflection._residual import NO_BOX, _grid, _key, _rays_kernel

    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 3))
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    rows, side = _grid(16)
    point, ray = np.repeat(np.arange(50), 16), np.tile(np.arange(16), 50)
    whole = np.empty((800, 8))
    _rays_kernel(x, n, point, ray, np.array([0.5, 0.0, 0.0]), 0.7, 0.8, _key(7, 2), rows, side, 1e-4, full,
                 np.zeros(3), NO_BOX, whole)
    pick = np.array([3, 517, 799, 100])
    part = np.empty((4, 8))
    _rays_kernel(x, n, point[pick], ray[pick], np.array([0.5, 0.0, 0.0]), 0.7, 0.8, _key(7, 2), rows, side, 1e-4, full,
                 np.zeros(3), NO_BOX, part)
    np.testing.assert_array_equal(part, whole[pick])
    np.testing.assert_allclose(np.linalg.norm(whole[:, 3:6], axis=1), 1.0, atol=1e-12)


@pytest.fixture(scope="module")
def two_balls(tmp_path_factory):
    """The quick ball over a floor with a second ball (the first one's precomputation), the options QUICK."""
    from prtlab.cache import Cache
    from prtlab.interreflection import Interreflection
    from prtlab.scene import SceneObject, Transform
    from tests.scenes import ball_over_floor

    quick = dict(n_radii=8, resolution=8, degree=31, n_lights=64, n_basis=8, residual_rays=16)
    base = ball_over_floor({"type": "diffuse", "albedo": [0.8, 0.3, 0.3]})
    pre = Interreflection.precompute(base, quick, cache=Cache(tmp_path_factory.mktemp("cache"), progress=False),
                                     progress=False)
    other = SceneObject("other", base.object("ball").mesh, Transform(translate=np.array([1.2, 0.6, 0.3])),
                        base.object("ball").material)
    scene = type(base)(objects=[*base.objects, other], lights=base.lights, camera=base.camera)
    return scene, pre.options, {**pre.data, "other": pre.data["ball"]}


@pytest.mark.parametrize("where", [[-1.1, 0.7, -0.6], [0.9, 0.8, 0.2]])
def test_moving_an_object_recasts_only_what_it_may_change(two_balls, where):
    """Frames that move one ball (far, then against the other ball): the residual gather casts fewer rays than
    a fresh shade and the light equals the fresh shade's to 1e-12; the fast gather equals the reference."""
    from prtlab.interreflection import Interreflection
    from prtlab.pipeline import FrameState
    from prtlab.scene import Transform

    scene, options, data = two_balls
    ir = Interreflection(scene, options, data)
    state = FrameState.from_scene(scene)
    ir.shade(state, bounces=2)
    state.transforms["other"] = Transform(translate=np.array(where), rotate_deg=np.array([0.0, 30.0, 10.0]))
    moved = ir.shade(state, bounces=2)
    fresh_ir = Interreflection(scene, options, data)
    fresh = fresh_ir.shade(state, bounces=2)
    assert 0 < moved.info["residual_rays_cast"] < fresh.info["residual_rays_cast"]
    for name in ("floor", "ball", "other"):
        np.testing.assert_allclose(moved.indirect[name], fresh.indirect[name], rtol=1e-12,
                                   atol=1e-12 * np.abs(fresh.indirect[name]).max())
    relit = ir.shade(state, bounces=2)
    assert relit.info["residual_rays_cast"] == 0
    # the fast gather of every receiver against the reference sum over its hits
    geo = ir.reuse.frame[1][0]
    rng = np.random.default_rng(0)
    residuals = {o.name: rng.normal(size=(o.n_vertices, 1, 3)) for o in ir.objects}
    phi = {o.name: {s.name: None for s in ir.objects if s is not o} for o in ir.objects}
    for r in ir.objects:
        fast = ir._residual_light(geo, r, residuals, phi[r.name])
        ref = ir._residual_light(geo, r, residuals, phi[r.name], method="reference")
        np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())


# ------------------------------------------------------------------ near hits: the source's radiance at the hit


def _lit_plane_gather(light_height: float, near: float, n_rays: int = 4096):
    """A 2 x 2 Lambertian plane (y = 0, 3 x 3 vertices: far coarser than the light's pool) under a point light
    ``light_height`` above (0.5, 0, 0.5), a cell's centre; a receiver point 0.1 above (0.4, 0, 0.45) facing down.
    Returns the gathered ``L`` with every hit interpolated from the vertices, with the near hits' correction,
    the per-ray values of the latter (for its standard error) and the closed form's quadrature."""
    from prtlab.interreflection._direct_rays import ray_traced_direct
    from prtlab.interreflection._residual import near_hit_correction, near_hits
    from prtlab.scene import PointLight

    plane = builtin_mesh("plane", size=[2.0, 2.0], resolution=[2, 2])
    caster = RayCaster([plane])
    verts, vn = np.asarray(plane.vertices, float), np.asarray(plane.vertex_normals, float)
    light = PointLight(position=np.array([0.5, light_height, 0.5]), intensity=np.array([2.0, 2.0, 2.0]))
    x, n = np.array([[0.4, 0.1, 0.45]]), np.array([[0.0, -1.0, 0.0]])
    sources = {0: (np.asarray(plane.faces), vn, LAMBERT, np.zeros(3), np.sqrt(2.0))}
    hits = residual_hits(x, n, LAMBERT, caster, sources, n_rays)[0]
    colour = np.asarray(LAMBERT.colour, float)[None]
    lam = brdf.lambert([0.5, 0.5, 0.5])
    vertex = ray_traced_direct(verts, vn, vn, lam, LAMBERT, caster, [light], 1)[0] * colour
    index, at, normals = near_hits(hits, x, verts, vn, near)
    exact = ray_traced_direct(at, normals, normals, lam, LAMBERT, caster, [light], 1)[0] * colour
    interpolated = gather_residual(hits, vertex, 1)
    corrected = interpolated + near_hit_correction(hits, index, exact, vertex, 1)
    # per ray (the misses carry 0): what the corrected gather sums
    m = _grid_size(n_rays)
    per_ray = np.zeros(m)
    per_ray[hits.rays[index] % m] = hits.factor[index, 0, 0] * exact[:, 0, 0]
    # closed form: L = g' h colour int (n . w)+ cos_y / r^2 * g I cos_l / d^2 dA over the plane (midpoint rule)
    k = 1200
    u = (np.arange(k) + 0.5) / k * 2.0 - 1.0
    yx, yz = np.meshgrid(u, u, indexing="ij")
    dx, dz = yx - x[0, 0], yz - x[0, 2]
    r2 = dx * dx + dz * dz + x[0, 1] ** 2
    cos_x = cos_y = x[0, 1] / np.sqrt(r2)
    lx, lz = yx - 0.5, yz - 0.5
    d2 = lx * lx + lz * lz + light_height**2
    g = 1.0 / np.pi  # Lambert: g = 1 / pi, h = 1
    src = g * 2.0 * (light_height / np.sqrt(d2)) / d2
    quadrature = g * 0.5 * float(np.sum(cos_x * cos_y / r2 * src)) * (2.0 / k) ** 2
    return interpolated[0, 0, 0], corrected[0, 0, 0], per_ray, quadrature, len(index), len(hits.rows)


def _grid_size(n: int) -> int:
    side = max(1, int(np.sqrt(n)))
    return max(1, n // side) * side


@pytest.mark.parametrize("light_height", [0.25, 0.6])
def test_near_hits_carry_the_sources_radiance_at_the_hit(light_height):
    """The gather with every hit near (``near`` = 2 edge lengths covers the 2 x 2 plane) equals the closed form
    ``L = g' h colour int cos_x cos_y / r^2 L_src dA`` of a point light over a plane within 4 standard errors of
    the ray sum (per-ray values, independent rays: a stratified grid only lowers the variance); the vertex
    interpolation alone (the mutation of leaving the correction out) misses by far more: the 3 x 3 vertices
    cannot hold the light's pool."""
    interpolated, corrected, per_ray, quadrature, n_near, n_hits = _lit_plane_gather(light_height, 2.0)
    assert n_near == n_hits > 0
    tol = 4.0 * np.sqrt(len(per_ray)) * np.std(per_ray)  # the sum of m per-ray values: sqrt(m) of their std
    assert abs(corrected - quadrature) <= tol, (corrected, quadrature, tol)
    assert abs(interpolated - quadrature) > 5.0 * tol, (interpolated, quadrature, tol)


def test_near_hits_are_those_nearer_than_the_edge_multiple():
    """``near_hits`` keeps exactly the hits whose distance to their receiver point is below ``near`` times the
    hit triangle's longest edge, and gives the hit points on the plane with its normal."""
    from prtlab.interreflection._residual import near_hits

    plane = builtin_mesh("plane", size=[2.0, 2.0], resolution=[2, 2])
    verts, vn = np.asarray(plane.vertices, float), np.asarray(plane.vertex_normals, float)
    x, n = np.array([[0.4, 0.1, 0.45]]), np.array([[0.0, -1.0, 0.0]])
    sources = {0: (np.asarray(plane.faces), vn, LAMBERT, np.zeros(3), np.sqrt(2.0))}
    hits = residual_hits(x, n, LAMBERT, RayCaster([plane]), sources, 256)[0]
    index, at, normals = near_hits(hits, x, verts, vn, 0.2)  # 0.2 sqrt(2): about 0.28
    every = np.einsum("hc,hcx->hx", hits.bary, verts[hits.vertices])
    gap = np.linalg.norm(every - x, axis=1)
    np.testing.assert_array_equal(index, np.flatnonzero(gap < 0.2 * np.sqrt(2.0)))
    assert 0 < len(index) < len(gap)
    np.testing.assert_allclose(at[:, 1], 0.0, atol=1e-6)
    np.testing.assert_allclose(normals, np.tile([0.0, 1.0, 0.0], (len(index), 1)), atol=1e-12)
    with pytest.raises(ValueError, match="near must be a positive"):
        near_hits(hits, x, verts, vn, 0.0)


def test_residual_near_options_are_validated():
    with pytest.raises(ValueError, match="residual_near"):
        InterreflectionOptions(residual_near=-1.0)
    with pytest.raises(TypeError, match="residual_near"):
        InterreflectionOptions(residual_near="far")
    with pytest.raises(ValueError, match="residual_near_samples"):
        InterreflectionOptions(residual_near_samples=0)
    with pytest.raises(TypeError, match="residual_near_probe"):
        InterreflectionOptions(residual_near_probe=1)


@pytest.fixture(scope="module")
def low_ball():
    """The quick ball over floor (``tests/interreflection/test_pipeline.py``), the ball 5 cm above the floor
    under a small area light, precomputed without a cache."""
    from prtlab.interreflection import Interreflection
    from prtlab.scene import AreaLight
    from tests.interreflection.test_pipeline import QUICK
    from tests.scenes import ball_over_floor

    s = ball_over_floor({"type": "diffuse", "albedo": [0.8, 0.3, 0.3]})
    s.objects[1].transform.translate[1] = 0.55
    s.lights = [AreaLight(center=np.array([0.3, 2.5, 0.2]), u=np.array([0.1, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.1]),
                          radiance=np.array([100.0, 100.0, 100.0]))]
    return Interreflection.precompute(s, QUICK, cache=False, progress=False)


def test_the_pipeline_adds_the_near_hits_on_the_first_bounce_only(low_ball):
    """``residual_near`` changes the first bounce where hits are near, is reused while the poses and lights stand,
    made again when the light moves, and does nothing with ``shadows="sh"`` or ``residual_rays=0``."""
    import dataclasses

    from prtlab.interreflection import Interreflection
    from prtlab.pipeline import FrameState

    def shaded(bounces=1, **options):
        ir = Interreflection(low_ball.scene, dataclasses.replace(low_ball.options, **options), low_ball.data)
        return ir, ir.shade(bounces=bounces)

    ir, on = shaded()
    _, off = shaded(residual_near=0)
    assert on.info["residual_near_hits"] > 0 and off.info["residual_near_hits"] == 0
    assert not np.allclose(on.indirect["ball"], off.indirect["ball"])
    np.testing.assert_array_equal(on.direct["ball"], off.direct["ball"])
    again = ir.shade(bounces=1)  # the same state: the near hits' correction is reused, no hit evaluated again
    assert again.info["residual_near_hits"] == 0
    np.testing.assert_array_equal(again.indirect["ball"], on.indirect["ball"])
    state = FrameState.from_scene(low_ball.scene)
    state.lights = [dataclasses.replace(state.lights[0], center=state.lights[0].center + np.array([0.5, 0.0, 0.0]))]
    assert ir.shade(state, bounces=1).info["residual_near_hits"] > 0
    for options in ({"shadows": "sh"}, {"residual_rays": 0}):
        with_near, without = shaded(**options)[1], shaded(residual_near=0, **options)[1]
        np.testing.assert_array_equal(with_near.indirect["ball"], without.indirect["ball"])
        assert with_near.info["residual_near_hits"] == 0


def test_residual_whole_makes_near_points_independent_of_the_basis(low_ball, monkeypatch):
    """With ``residual_whole`` a floor point with a near hit on the ball (the floor's only source) gathers the
    ball's whole radiance by rays, ``gather(P(colour L) + r) = gather(colour L)``, whatever the ball's PCA basis:
    its first bounce is the same with N = 8 and N = 2 basis functions (to float64 rounding: the gather's
    weights and the stacked irradiance in float64, the identity's precision); without the option it is not."""
    import dataclasses

    from prtlab.interreflection import Interreflection, _pipeline, _residual

    monkeypatch.setattr(_residual, "PACKED_WEIGHTS", np.float64)
    monkeypatch.setattr(_pipeline, "STACKED_IRRADIANCE", np.float64)

    def floor_light(n_basis, whole):
        ir = Interreflection(low_ball.scene, dataclasses.replace(low_ball.options, residual_whole=whole),
                             low_ball.data)
        ir = ir.truncated(n_basis=n_basis) if n_basis else ir
        res = ir.shade(bounces=1)
        names = [o.name for o in ir.objects]
        near = ir.reuse.near_hits[("floor", names.index("ball"))]
        return res.indirect["floor"], np.unique(near[0].rows[near[2][0]])

    full, rows = floor_light(None, True)
    cut, rows_cut = floor_light(2, True)
    np.testing.assert_array_equal(rows, rows_cut)
    assert len(rows) > 0
    np.testing.assert_allclose(cut[rows], full[rows], rtol=1e-9, atol=1e-12)
    assert not np.allclose(floor_light(2, False)[0][rows], floor_light(None, False)[0][rows], rtol=1e-3)
    with pytest.raises(TypeError, match="residual_whole"):
        InterreflectionOptions(residual_whole=1)


def _casts_before_and_after_a_move(seps, r, full, **kwargs):
    """Receiver ``r``'s residual hits (``residual_hits(..., **kwargs)``) in ``_objects``' poses, a full cast (the
    ball a source of itself), then after the box moves next to the ball, the incremental cast (``previous``), and
    the rays both cast."""
    meshes, poses, moves = _objects()
    after_poses = [poses[0], poses[1], moves["next to the ball"]]
    before, after = RayCaster(meshes, transforms=poses), RayCaster(meshes, transforms=after_poses)
    x, n = _receiver(meshes, poses, r)
    indices = [i for i in range(3) if i != r or r == 1]
    src_before = _sources(meshes, poses, indices, seps)
    src_after = _sources(meshes, after_poses, indices, seps)
    stats = {}
    old = residual_hits(x, n, seps[r], before, src_before, 64, seed=3, stats=stats, full=full, **kwargs)
    moved = {2: np.stack([_sphere(before, src_before[2]), _sphere(after, src_after[2])])} if r != 2 else None
    new = residual_hits(x, n, seps[r], after, src_after, 64, seed=3, previous=old if r != 2 else None,
                        moved=moved, stats=stats, full=full, **kwargs)
    return old, new, stats["rays_cast"]


def _assert_same_casts(one, other):
    """Two runs of :func:`_casts_before_and_after_a_move`: the same rays cast and every array bit for bit."""
    assert one[2] == other[2]
    for a_hits, b_hits in zip(one[:2], other[:2]):
        assert set(a_hits) == set(b_hits) and a_hits
        for i in a_hits:
            for a, b in zip(a_hits[i].arrays(), b_hits[i].arrays()):
                assert a.dtype == b.dtype
                np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("full", [0.0, 0.3])
@pytest.mark.parametrize("seps", [(LAMBERT, PHONG, LAMBERT), (PHONG, PHONG, PHONG)])
@pytest.mark.parametrize("r", [0, 1, 2])
def test_fused_cast_equals_the_reference_cast(seps, r, full):
    """``residual_hits``'s kernels (rays made, traced and weighed in numba) give the arrays of the reference (rays
    traced through ``RayCaster.closest_hit``, weighed with numpy), bit for bit, and count the same rays: a full cast
    (the ball a source of itself) and, after the box moves, the incremental cast. A Lambertian receiver and source
    take ``_weigh_hit``'s level path (no local frames or angles), the others the tables'."""
    from prtlab.interreflection._residual import _weighing

    meshes, poses, _ = _objects()
    sources = _sources(meshes, poses, range(3), seps)
    for s in range(3):
        assert _weighing(seps[r], sources[s])[-1] == (seps[r] is LAMBERT and seps[s] is LAMBERT)
    _assert_same_casts(_casts_before_and_after_a_move(seps, r, full, method="reference"),
                       _casts_before_and_after_a_move(seps, r, full, method="numba"))


def test_residual_hits_method_is_validated():
    meshes, poses, _ = _objects()
    x, n = _receiver(meshes, poses, 0)
    with pytest.raises(ValueError, match="method"):
        residual_hits(x, n, LAMBERT, RayCaster(meshes, transforms=poses), {}, 16, method="embree")


@pytest.mark.parametrize("near", [0.5, 2.0, 8.0])
def test_near_hits_kernel_equals_the_reference(near):
    """``near_hits``'s kernels select the same hits as its numpy tier and give the same points and normals, bit for
    bit, on every receiver and source of the floor, ball and box."""
    from prtlab.interreflection._residual import near_hits

    meshes, poses, _ = _objects()
    seps = (LAMBERT, PHONG, LAMBERT)
    caster = RayCaster(meshes, transforms=poses)
    selected = 0
    for r in range(3):
        x, n = _receiver(meshes, poses, r)
        srcs = _sources(meshes, poses, [i for i in range(3) if i != r], seps)
        for i, hits in residual_hits(x, n, seps[r], caster, srcs, 64, seed=2).items():
            ref = near_hits(hits, x, caster.world_vertices(i), srcs[i][1], near, method="reference")
            fast = near_hits(hits, x, caster.world_vertices(i), srcs[i][1], near)
            for a, b in zip(ref, fast):
                assert a.dtype == b.dtype
                np.testing.assert_array_equal(a, b)
            selected += len(ref[0])
    assert selected > 0


@pytest.mark.parametrize("options", [{}, {"residual_near": 0}, {"residual_rays": 0}, {"residual_whole": True}])
def test_fused_bounces_equal_the_reference_tier(low_ball, options, monkeypatch):
    """Three bounces by :func:`bounce_rgb` (one pass per receiver: Eq. 12, the residual gather, the near hits'
    correction), its gather weights and stacked irradiance in float64, equal the reference tier's (BLAS's
    product, the float64 sum over the hits) to 1e-12 (float32: ``test_packed_float32_gather_within_its_rounding_bound``,
    ``test_float32_stacked_irradiance_within_its_rounding_bound``)."""
    import dataclasses

    from prtlab.interreflection import _pipeline, _residual

    monkeypatch.setattr(_residual, "PACKED_WEIGHTS", np.float64)
    monkeypatch.setattr(_pipeline, "STACKED_IRRADIANCE", np.float64)

    from prtlab.interreflection import Interreflection
    from prtlab.pipeline import FrameState

    ir = Interreflection(low_ball.scene, dataclasses.replace(low_ball.options, **options), low_ball.data)
    state = FrameState.from_scene(low_ball.scene)
    ir.shade(state, bounces=1)
    geo = ir.reuse.frame[1][0]
    light_k = {o.name: ir.reuse.direct_rays[o.name]["light_k"] for o in ir.objects}
    phi, _ = ir.basis_irradiance_step(geo, ir.reuse.frame[1][1])
    fast = ir._bounces(geo, phi, light_k, 3, state.lights)[0]
    ref = ir._bounces(geo, phi, light_k, 3, state.lights, method="reference")[0]
    for name, expected in ref.items():
        assert np.abs(expected).max() > 0
        np.testing.assert_allclose(fast[name], expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())


def _random_gathers(rng, n_r, sizes):
    """Random operators (K = K' = 1, float32 barycentrics) of sources with ``sizes`` vertices on ``n_r`` points,
    their stacked residual and offsets."""
    from prtlab.interreflection._residual import GatherOperator

    def operator(n_s):
        counts = rng.integers(0, 6, n_r)
        n_h = int(counts.sum())
        faces = rng.integers(0, n_s, (9, 3)).astype(np.int32)
        return GatherOperator(np.concatenate([[0], np.cumsum(counts)]).astype(np.int64), faces,
                              rng.integers(0, 9, n_h).astype(np.int32),
                              (rng.random((n_h, 2)) * 0.5).astype(np.float32), rng.normal(size=(n_h, 1, 1)))

    return [operator(n) for n in sizes], rng.normal(size=(sum(sizes), 3)), np.cumsum([0] + sizes[:-1])


def test_bounce_rgb_equals_apply_gather():
    """:func:`bounce_rgb` on random operators, packed with float64 weights, equals ``stacked @ w`` plus
    :func:`apply_gather` per source plus the extra term to 1e-12, and with no source the product alone; an
    empty receiver gives an empty result."""
    from prtlab.interreflection._residual import apply_gather, bounce_rgb, pack_operators

    rng = np.random.default_rng(3)
    n_r, n_m, sizes = 40, 24, [7, 11]
    ops, residual, offsets = _random_gathers(rng, n_r, sizes)
    stacked, w, extra = rng.normal(size=(n_r, n_m)), rng.normal(size=(n_m, 3)), rng.normal(size=(n_r, 3))
    expected = (stacked @ w)[:, None]
    gathered = np.zeros((n_r, 1, 3))
    for op, a, n in zip(ops, offsets, sizes):
        apply_gather(op, residual[a:a + n].reshape(n, 1, 3), gathered)
    expected = (expected + gathered + extra[:, None])[:, 0]
    packed = pack_operators(ops, [0, 1], offsets, dtype=np.float64)
    np.testing.assert_allclose(bounce_rgb(stacked, w, ops, [0, 1], residual, offsets, extra, packed=packed),
                               expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(bounce_rgb(stacked, w, [], [], None, None), stacked @ w, rtol=1e-12, atol=1e-12)
    assert bounce_rgb(np.zeros((0, n_m)), w, ops, [0, 1], residual, offsets).shape == (0, 3)


def _merged_bounce(stacked, wt, starts, rows, weights, x):
    """The bounce over :func:`pack_operators`' one list of terms a point: ``_bounce_kernel`` with that list as its
    one segment (the loop it ran before it read segments)."""
    from prtlab.interreflection._residual import _bounce_kernel

    out = np.empty((len(stacked), 3))
    _bounce_kernel(stacked, np.ascontiguousarray(wt.T), starts.reshape(1, -1), rows, weights, x,
                   np.arange(len(x), dtype=np.int64), np.empty((len(x), 4), weights.dtype), np.zeros((0, 3)), out)
    return out


def test_packed_gather_segments_equal_one_merged_list():
    """:class:`PackedGather` re-packs only the operators that changed, and :func:`bounce_rgb` over its segments
    equals, bit for bit, the sum over :func:`pack_operators`' one merged list (the terms of every source in
    order, each point's sum in the same order): when packed whole, after one source's operator changes (the
    others' terms reused, not re-packed), after the first and last change, when none does, with more room than
    the arrays hold (made again), and with a source's rows moved."""
    import dataclasses

    from prtlab.interreflection._residual import PackedGather, bounce_rgb, pack_operators

    rng = np.random.default_rng(21)
    n_r, n_m, sizes = 200, 12, [30, 45, 20, 60]
    sources = [0, 1, 2, 3]
    ops, residual, offsets = _random_gathers(rng, n_r, sizes)
    stacked, w = rng.normal(size=(n_r, n_m)), rng.normal(size=(n_m, 3))
    packed = PackedGather()

    def check(ops, n_segments, offsets=offsets):
        assert packed.update(ops, sources, offsets) is packed
        assert packed.starts.shape == (n_segments, n_r + 1)
        merged = pack_operators(ops, sources, offsets)
        expected = _merged_bounce(stacked, w, *merged, residual)
        np.testing.assert_array_equal(bounce_rgb(stacked, w, ops, sources, residual, offsets, packed=packed),
                                      expected)
        np.testing.assert_array_equal(bounce_rgb(stacked, w, ops, sources, residual, offsets, packed=merged),
                                      expected)
        np.testing.assert_array_equal(bounce_rgb(stacked, w, ops, sources, residual, offsets), expected)

    check(ops, 1)
    more, _, _ = _random_gathers(rng, n_r, sizes)
    ops = ops[:2] + [more[2]] + ops[3:]  # one source's operator changes: three segments
    check(ops, 3)
    rows, segments = packed.rows, packed.starts.copy()
    kept = [rows[a:b].copy() for a, b in zip(segments[:, 0], segments[:, -1])]
    for _ in range(3):  # the same source changes again and again: its own segment alone is re-packed, in place
        ops = ops[:2] + [dataclasses.replace(more[2], factor=rng.normal(size=more[2].factor.shape))] + ops[3:]
        check(ops, 3)
        assert packed.rows is rows
        np.testing.assert_array_equal(packed.starts, segments)
        for s in (0, 2):
            np.testing.assert_array_equal(rows[segments[s, 0]:segments[s, -1]], kept[s])
    check(ops, 3)  # nothing changes
    ops = [more[0]] + ops[1:3] + [more[3]]  # the first and last change: the first segment splits in two
    check(ops, 4)
    grown, _, _ = _random_gathers(np.random.default_rng(5), 4 * n_r, sizes)
    big = dataclasses.replace(grown[1], starts=np.concatenate([[0], grown[1].starts[4:4 * n_r + 1:4]]))
    ops = ops[:1] + [big] + ops[2:]  # more terms than the arrays have room for: made again
    check(ops, 4)
    assert packed.rows is not rows
    check(ops, 4, offsets=offsets + np.array([0, 0, 0, 1]))  # the last source's rows moved: it is re-packed
    check(list(reversed(ops)), 1)  # other operators throughout: packed whole


def _gather_in_order(starts, rows, weights, x):
    """The packed gather's specification, one Python float at a time: per point ``sum_t sum_j w[t, j] x[rows[t,
    j]]`` over its terms of every segment in order (``starts`` (S, V + 1)), each residual value rounded to the
    weights' type as the kernel's table holds it."""
    out = np.zeros((starts.shape[1] - 1, 3))
    held = weights.dtype.type
    for v in range(len(out)):
        g = [0.0, 0.0, 0.0]
        for s in range(len(starts)):
            for t in range(starts[s, v], starts[s, v + 1]):
                for j in range(3):
                    c = float(weights[t, j])
                    for k in range(3):
                        g[k] += c * float(held(x[rows[t, j], k]))
        out[v] = g
    return out


def test_packed_gather_compact_residual_equals_the_stacked_rows(monkeypatch):
    """:class:`PackedGather`'s compact residual holds each stacked residual row its terms read once (uint16 row
    numbers; int32 past ``SHORT_ROWS``), and :func:`bounce_rgb` over it equals, bit for bit, the gather in order
    over :func:`pack_operators`' stacked rows (``_gather_in_order``): packed whole, after operators change (the
    rows they read anew appended), and after growing past ``COMPACT_GROWTH`` (every operator packed again, over
    the rows read only); with float32 weights and with float64 ones."""
    import dataclasses

    from prtlab.interreflection import _residual
    from prtlab.interreflection._residual import PackedGather, bounce_rgb, pack_operators

    rng = np.random.default_rng(34)
    n_r, n_m, sizes = 120, 4, [50, 80, 40]
    sources = [0, 1, 2]
    ops, residual, offsets = _random_gathers(rng, n_r, sizes)
    stacked, w = np.zeros((n_r, n_m), np.float32), np.zeros((n_m, 3))  # the dot product adds exact zeros

    def read_rows(ops):
        return np.unique(np.concatenate([a + op.faces[op.triangles].ravel() for op, a in zip(ops, offsets)]))

    def check(packed, ops, dtype, exact_set):
        assert packed.update(ops, sources, offsets) is packed
        starts, rows, weights, residual_rows = packed.arrays()
        assert rows.dtype == dtype
        assert len(np.unique(residual_rows)) == len(residual_rows)
        assert set(read_rows(ops)) <= set(residual_rows)
        if exact_set:
            np.testing.assert_array_equal(np.sort(residual_rows), read_rows(ops))
        merged = pack_operators(ops, sources, offsets, dtype=packed.dtype)
        expected = _gather_in_order(merged[0].reshape(1, -1), merged[1], merged[2], residual)
        np.testing.assert_array_equal(bounce_rgb(stacked, w, ops, sources, residual, offsets, packed=packed), expected)
        terms = np.concatenate([np.arange(starts[s, v], starts[s, v + 1]) for v in range(n_r)
                                for s in range(len(starts))]).astype(np.int64)
        np.testing.assert_array_equal(residual_rows[rows[terms]], merged[1])  # the same stacked rows, term by term
        np.testing.assert_array_equal(weights[terms], merged[2])

    packed = PackedGather()
    check(packed, ops, np.uint16, True)
    more, _, _ = _random_gathers(rng, n_r, sizes)
    ops = ops[:1] + [more[1]] + ops[2:]
    check(packed, ops, np.uint16, False)  # more rows appended, within the growth allowed
    check(packed, ops[:1] + [more[1]] + [more[2]], np.uint16, False)  # a third segment
    assert packed.starts.shape[0] == 3
    monkeypatch.setattr(_residual, "COMPACT_GROWTH", 1.0)
    monkeypatch.setattr(_residual, "COMPACT_SLACK", 0)
    ops = ops[:1] + [more[1]] + [dataclasses.replace(more[2], faces=(more[2].faces + 7) % sizes[2])]
    assert not set(read_rows(ops)) <= set(packed.residual_rows)  # rows read anew: grown, packed whole again
    check(packed, ops, np.uint16, True)
    assert packed.starts.shape[0] == 1
    monkeypatch.setattr(_residual, "SHORT_ROWS", 16)
    check(PackedGather(), ops, np.int32, True)  # too many rows for uint16
    check(PackedGather(np.float64), ops, np.int32, True)  # float64 weights: the residual read as it is


def test_packed_float32_gather_within_its_rounding_bound():
    """The default float32 weights (``PACKED_WEIGHTS``), with the residual rows read in float32 too, move a point's
    gather by at most ``2 * 2**-24 + 2**-48`` times the sum of its terms' magnitudes ``sum_h |factor b_j r_j|``
    (each weight and each residual value rounded once, relative ``2**-24``), plus the float64 sums' own rounding
    (at most 45 terms a point here: ``64 * 2**-53`` of it), against float64 weights and rows of the same terms."""
    from prtlab.interreflection._residual import _gather_rows, bounce_rgb, pack_operators

    rng = np.random.default_rng(8)
    n_r, n_m, sizes = 300, 5, [40, 70, 25]
    ops, residual, offsets = _random_gathers(rng, n_r, sizes)
    stacked, w = np.zeros((n_r, n_m)), np.zeros((n_m, 3))
    args = ([0, 1, 2], residual, offsets)
    exact = bounce_rgb(stacked, w, ops, *args, packed=pack_operators(ops, [0, 1, 2], offsets, dtype=np.float64))
    rounded = bounce_rgb(stacked, w, ops, *args)
    magnitude = np.zeros((n_r, 3))
    for op, a in zip(ops, offsets):  # sum_h |c| (b0 |x0| + u |x1| + v |x2|): the gather of |c| over |r|
        _gather_rows(op.starts, op.faces, op.triangles, op.uv, np.abs(op.factor.reshape(-1)), a, np.abs(residual),
                     magnitude)
    assert np.abs(rounded - exact).max() > 0  # the rounding is there to bound
    assert np.all(np.abs(rounded - exact) <= (2.0 * 2.0**-24 + 2.0**-48 + 64 * 2.0**-53) * magnitude)


def test_float32_stacked_irradiance_within_its_rounding_bound():
    """``stacked @ w`` of :func:`bounce_rgb` (summed in any order, ``_dot_rgb``) against the correctly rounded
    sums of the float64 products (``math.fsum``): within ``(n_m + 1) 2**-53 sum_m |Phi_m| |w_m|`` (the sum's
    ``n_m - 1`` roundings, the products', the final one); with float32 stacked basis irradiance
    (``STACKED_IRRADIANCE``, each value rounded once) within ``2**-24`` of that magnitude more (``n_m + 2``
    covering the second-order terms)."""
    from prtlab.interreflection._residual import bounce_rgb

    rng = np.random.default_rng(11)
    n_r, n_m = 500, 192
    stacked, w = rng.normal(size=(n_r, n_m)), rng.normal(size=(n_m, 3))
    exact = np.array([[math.fsum(stacked[v] * w[:, c]) for c in range(3)] for v in range(n_r)])
    magnitude = np.abs(stacked) @ np.abs(w)
    summed = bounce_rgb(stacked, w, [], [], None, None)
    rounded = bounce_rgb(stacked.astype(np.float32), w, [], [], None, None)
    assert np.all(np.abs(summed - exact) <= (n_m + 1) * 2.0**-53 * magnitude)
    assert np.abs(rounded - exact).max() > 0
    assert np.all(np.abs(rounded - exact) <= (2.0**-24 + (n_m + 2) * 2.0**-53) * magnitude)


def test_moving_an_object_recasts_only_the_near_hits_it_may_shadow(low_ball):
    """A third object (last in the list) moves beside the low ball: the near hits' light is cast again only where
    a shadow ray may meet it (and on its own hits), and the corrections equal a fresh shade's bit for bit."""
    from prtlab.interreflection import Interreflection
    from prtlab.pipeline import FrameState
    from prtlab.scene import SceneObject, Transform

    base = low_ball.scene
    other = SceneObject("other", base.object("ball").mesh, Transform(translate=np.array([1.3, 0.55, -1.3])),
                        base.object("ball").material)
    scene = type(base)(objects=[*base.objects, other], lights=base.lights, camera=base.camera)
    data = {**low_ball.data, "other": low_ball.data["ball"]}
    ir = Interreflection(scene, low_ball.options, data)
    state = FrameState.from_scene(scene)
    ir.shade(state, bounces=1)
    state.transforms["other"] = Transform(translate=np.array([1.25, 0.55, -1.3]))
    moved = ir.shade(state, bounces=1)
    fresh_ir = Interreflection(scene, low_ball.options, data)
    fresh = fresh_ir.shade(state, bounces=1)
    assert 0 < moved.info["residual_near_rays_cast"] < fresh.info["residual_near_rays_cast"]
    for name, expected in fresh_ir.reuse.near_exact["corrections"].items():
        np.testing.assert_array_equal(ir.reuse.near_exact["corrections"][name], expected)
        np.testing.assert_array_equal(moved.indirect[name], fresh.indirect[name])


def test_near_hits_take_the_answer_their_triangles_vertices_agree_on(low_ball):
    """``residual_near_probe``: a near hit whose triangle's vertices all have a light's samples clear (and some lit)
    or all blocked in the direct light takes that answer without rays; the others are cast as without the option,
    so the corrections differ only at the decided hits, and fewer rays are cast."""
    import dataclasses

    from prtlab.interreflection import Interreflection

    shades = {}
    for probe in (False, True):
        ir = Interreflection(low_ball.scene, dataclasses.replace(low_ball.options, residual_near_probe=probe),
                             low_ball.data)
        shades[probe] = (ir, ir.shade(bounces=1))
    (off_ir, off), (on_ir, on) = shades[False], shades[True]
    assert on.info["residual_near_hits"] == off.info["residual_near_hits"] > 0
    assert 0 < on.info["residual_near_rays_cast"] < off.info["residual_near_rays_cast"]
    given = []
    for i, source in enumerate(on_ir.objects):
        if i not in on_ir.reuse.near_sources:
            continue
        S_on, _, mask_on, decided = on_ir.reuse.near_sources[i]["terms"][0]
        S_off, _, mask_off, _ = off_ir.reuse.near_sources[i]["terms"][0]
        given.append(decided)
        np.testing.assert_array_equal(mask_on[decided == 0], mask_off[decided == 0])
        np.testing.assert_array_equal(S_on[decided == 0], S_off[decided == 0])
        assert not mask_on[decided == 1].any() and np.all(S_on[decided == 2] == 0.0)
        # the decision: every corner of the hit triangle clear (and lit) or blocked in the frame's direct light
        entry = on_ir.reuse.direct_rays[source.name]["lights"][0]
        code = np.where(entry["mask"].all(axis=1), 2, np.where(~entry["mask"].any(axis=1) & entry["S"].any(axis=1),
                                                                1, 0))
        parts = [(hits, index) for r in on_ir.objects for (name, hits, index, _, _) in
                 _near_parts(on_ir, r.name, i)]
        corners = np.concatenate([code[hits.faces[hits.triangles[index]]] for hits, index in parts])
        np.testing.assert_array_equal(decided, np.where(np.ptp(corners, axis=1) == 0, corners[:, 0], 0))
    given = np.concatenate(given)
    assert np.any(given == 1) and np.any(given == 0)


def test_near_decided_kernel_equals_the_numpy_reference():
    """:func:`near_decided_kernel` gives the codes of ``_near_decided``'s numpy reference: rows all blocked, all
    clear with and without a lit entry, mixed, and no samples at all."""
    from types import SimpleNamespace

    from prtlab.interreflection import Interreflection

    rng = np.random.default_rng(5)
    for m in (0, 1, 9):
        mask = rng.random((40, m)) < 0.5
        mask[:10], mask[10:20] = True, False
        lit = rng.random((40, 2)) * (rng.random((40, 1)) < 0.6)
        lit[15:18] = 0.0
        corners = rng.integers(0, 40, (300, 3))
        corners[:10] = np.arange(10)[:, None]  # triangles of blocked vertices only
        ir = SimpleNamespace(reuse=SimpleNamespace(direct_rays={"s": {"lights": [{"mask": mask, "S": lit}]}}))
        got = Interreflection._near_decided(ir, "s", 0, corners)
        np.testing.assert_array_equal(got, Interreflection._near_decided(ir, "s", 0, corners, method="reference"))
        assert got.dtype == np.int8 and (m == 0 or np.any(got == 2))


def _near_parts(ir, receiver: str, source: int) -> list:
    """The ``(receiver, hits, index, points, normals)`` near-hit part of ``receiver`` on source number ``source``
    (empty when it has no near hit there), from ``ir``'s reuse."""
    cached = [value for (name, i), value in ir.reuse.near_hits.items() if name == receiver and i == source]
    return [(receiver, c[0], *c[2]) for c in cached if len(c[2][0])]


def test_light_terms_first_continues_the_streams():
    """``first=a`` on ``points[a:]`` gives rows ``a:`` of the whole call, in both tiers; a bad ``first`` fails."""
    from prtlab.geometry import RayCaster
    from prtlab.interreflection._direct_rays import light_terms, light_terms_reference
    from prtlab.scene import AreaLight

    rng = np.random.default_rng(5)
    points = np.c_[rng.uniform(-1, 1, 40), np.zeros(40), rng.uniform(-1, 1, 40)]
    normals = np.tile([0.0, 1.0, 0.0], (40, 1))
    blocker = (np.array([[-0.3, 0.5, -0.3], [0.3, 0.5, -0.3], [0.0, 0.5, 0.4]]), np.array([[0, 1, 2]]))
    caster = RayCaster([blocker])
    light = AreaLight(center=np.array([0.0, 2.0, 0.0]), u=np.array([0.3, 0, 0]), v=np.array([0, 0, 0.3]),
                      radiance=np.ones(3))
    lam = brdf.lambert([0.5, 0.5, 0.5])
    for terms in (light_terms, light_terms_reference):
        whole = terms(points, normals, normals, lam, LAMBERT, caster, light, 0, 16)
        parts = [terms(points[a:b], normals[a:b], normals[a:b], lam, LAMBERT, caster, light, 0, 16, first=a)
                 for a, b in ((0, 13), (13, 40))]
        for k in range(3):
            np.testing.assert_array_equal(np.concatenate([p[k] for p in parts]), whole[k])
        with pytest.raises(ValueError, match="first must be a non-negative int"):
            terms(points, normals, normals, lam, LAMBERT, caster, light, 0, 16, first=-1)


def test_a_convex_receiver_casts_no_rays_at_itself(low_ball):
    """The ball is convex: its rays leave it, so the residual gather leaves it out as its own source and its direct
    light's shadow rays leave it out as a blocker (they start in a tangent plane that supports it); the frame equals
    one that casts those rays (none hits the ball), with fewer rays cast."""
    import dataclasses

    from prtlab.interreflection import Interreflection
    from prtlab.pipeline import FrameState

    state = FrameState.from_scene(low_ball.scene)
    shades = {}
    for convex in (True, False):
        ir = Interreflection(low_ball.scene, dataclasses.replace(low_ball.options), low_ball.data)
        assert ir.convex == {"floor": False, "ball": True}
        ir.convex["ball"] = convex
        shades[convex] = ir.shade(state, bounces=2)
    for name in ("floor", "ball"):
        np.testing.assert_array_equal(shades[True].indirect[name], shades[False].indirect[name])
        np.testing.assert_array_equal(shades[True].direct[name], shades[False].direct[name])
    assert shades[True].info["residual_rays_cast"] < shades[False].info["residual_rays_cast"]
    assert shades[True].info["direct_rays_cast"] < shades[False].info["direct_rays_cast"]


def test_residual_cone_casts_fewer_rays_in_the_pipeline(low_ball):
    """``residual_cone`` takes the pipeline's residual rays down and leaves the result close (the same estimator
    with fewer rays where a source subtends little)."""
    import dataclasses

    from prtlab.interreflection import Interreflection
    from prtlab.pipeline import FrameState

    state = FrameState.from_scene(low_ball.scene)
    shades = {}
    for cone in (0.0, 0.5):
        ir = Interreflection(low_ball.scene, dataclasses.replace(low_ball.options, residual_cone=cone), low_ball.data)
        shades[cone] = ir.shade(state, bounces=1)
    assert shades[0.5].info["residual_rays_cast"] < shades[0.0].info["residual_rays_cast"]
    for name in ("floor", "ball"):
        a, b = shades[0.0].total[name], shades[0.5].total[name]
        assert np.sqrt(np.mean((a - b) ** 2)) <= 0.01 * np.sqrt(np.mean(a**2))


# ------------------------------------------------------------------ rays that cannot count are not made or cast


def test_facing_is_the_normal_of_a_flat_source_alone():
    """:func:`_facing`: a plane's shared unit normal; zeros for a curved source and for normals that differ by more
    than ``1e-12``."""
    from prtlab.interreflection._residual import _facing

    floor = builtin_mesh("plane", size=[2.0, 2.0], resolution=[4, 4])
    np.testing.assert_array_equal(_facing(floor.vertex_normals), np.asarray(floor.vertex_normals)[0])
    np.testing.assert_array_equal(_facing(builtin_mesh("icosphere", subdivisions=1).vertex_normals), np.zeros(3))
    bent = np.array(floor.vertex_normals, float)
    bent[3] += [1e-9, 0.0, 0.0]
    np.testing.assert_array_equal(_facing(bent), np.zeros(3))
    np.testing.assert_array_equal(_facing(np.zeros((0, 3))), np.zeros(3))


@pytest.mark.parametrize("cut", ["facing", "box"])
@pytest.mark.parametrize("method", ["numba", "reference"])
@pytest.mark.parametrize("r", [1, 2])
def test_rays_that_cannot_count_are_not_cast(monkeypatch, cut, method, r):
    """Each cut of rays that cannot count against casting them: ``"facing"``, rays along which the floor rises cannot
    meet its front (left uncast; the sources' boxes left out on both sides, which would leave most of them uncast
    too); ``"box"``, a ray cannot hit a source outside the box of its vertices (the rays that miss it left uncast, the
    others cut where they leave it). With the cut the hits (full and incremental casts) are those without it, bit
    for bit, and fewer rays are cast."""
    from prtlab.interreflection import _residual

    def no_box(points):
        return _residual.NO_BOX.reshape(2, 3)

    if cut == "facing":
        monkeypatch.setattr(_residual, "_points_box", no_box)
    meshes, poses, moves = _objects()
    seps = (LAMBERT, PHONG, LAMBERT)
    after_poses = [poses[0], poses[1], moves["next to the ball"]]
    before, after = RayCaster(meshes, transforms=poses), RayCaster(meshes, transforms=after_poses)
    x, n = _receiver(meshes, poses, r)
    indices = [i for i in range(3) if i != r]
    src_before, src_after = _sources(meshes, poses, indices, seps), _sources(meshes, after_poses, indices, seps)
    runs = {}
    for with_cut in (True, False):
        if not with_cut:
            if cut == "facing":
                monkeypatch.setattr(_residual, "_facing", lambda normals: np.zeros(3))
            else:
                monkeypatch.setattr(_residual, "_points_box", no_box)
        stats = {}
        old = residual_hits(x, n, seps[r], before, src_before, 64, seed=2, stats=stats, method=method, full=0.3)
        moved = None if r == 2 else {2: np.stack([_sphere(before, src_before[2]), _sphere(after, src_after[2])])}
        new = residual_hits(x, n, seps[r], after, src_after, 64, seed=2, stats=stats, method=method, full=0.3,
                            previous=None if r == 2 else old, moved=moved)
        runs[with_cut] = (old, new, stats["rays_cast"])
    assert runs[True][2] < runs[False][2]
    for fast, every in zip(runs[True][:2], runs[False][:2]):
        assert set(fast) == set(every) and 0 in fast
        for i in fast:
            for a, b in zip(fast[i].arrays(), every[i].arrays()):
                np.testing.assert_array_equal(a, b)


def test_clip_to_box_is_the_slab_test():
    """``_clip_to_box`` against a dense sampling of each segment: the samples inside the box lie within the clipped
    segment (so none of a segment called a miss); ``NO_BOX`` leaves every segment whole."""
    from prtlab.interreflection._residual import NO_BOX, _clip_to_box

    rng = np.random.default_rng(3)
    box = np.array([-1.0, -0.05, -2.0, 1.0, 0.05, 2.0])
    t = np.linspace(0.0, 1.0, 20_001)
    met = 0
    for _ in range(400):
        o, w = rng.uniform(-3.0, 3.0, 3), rng.normal(size=3)
        w[rng.integers(3)] *= rng.integers(2)  # a zero component now and then
        w /= np.linalg.norm(w)
        tmax = float(rng.uniform(0.0, 6.0))
        p = o + (tmax * t)[:, None] * w
        inside = np.all((p >= box[:3]) & (p <= box[3:]), axis=1)
        clipped = _clip_to_box(*o, *w, tmax, box)
        assert 0.0 <= clipped <= tmax
        if inside.any():
            assert tmax * t[inside].max() <= clipped * (1 + 1e-12) + 1e-12
        met += clipped > 0.0
        assert _clip_to_box(*o, *w, tmax, NO_BOX) == tmax
    assert 0 < met < 400


@pytest.mark.parametrize("full", [0.0, 0.5])
@pytest.mark.parametrize("seed", range(6))
def test_flagging_by_rows_equals_flagging_every_ray(seed, full):
    """``_flag_rows_kernel`` (``_recast_kernel``'s flagging: rays made only in the cells whose bands of angles may
    reach a moved sphere) gives ``_flag_kernel``'s flags, every ray made: random points, normals (some inside the
    source's sphere, some inside a moved sphere), moved spheres small and large, near and far."""
    from prtlab.interreflection._residual import NO_BOX, _flag_kernel, _flag_rows_kernel, _grid, _key

    rng = np.random.default_rng(seed)
    n_points = 400
    points = rng.uniform(-3.0, 3.0, size=(n_points, 3))
    normals = rng.normal(size=(n_points, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    centre, radius = rng.uniform(-1.0, 1.0, 3), float(rng.uniform(0.2, 2.0))
    bound = radius * 1.01
    spheres = np.concatenate([rng.uniform(-2.5, 2.5, size=(3, 3)), rng.uniform(0.01, 0.8, size=(3, 1))], axis=1)
    spheres[1, :3] = spheres[0, :3] + rng.normal(scale=1e-3, size=3)  # old and new pose of a small move
    points[:20] = spheres[0, :3] + rng.normal(scale=0.3 * spheres[0, 3], size=(20, 3))  # inside a moved sphere
    facing = np.zeros(3) if seed % 2 else np.array([0.0, 1.0, 0.0])
    # a flat box in the source's sphere on a third of the seeds (rays that miss it are not flagged), else none
    half = np.array([radius, 0.2 * radius, radius])
    box = NO_BOX if seed % 3 else np.concatenate([centre - half, centre + half])
    rows, side = _grid(64)
    candidates = np.arange(n_points)
    every, by_rows = (np.empty((n_points, rows * side), np.bool_) for _ in range(2))
    args = (points, normals, candidates, centre, radius, bound, _key(seed, 1), rows, side, 1e-4, full, facing, box,
            spheres)
    _flag_kernel(*args, every)
    _flag_rows_kernel(*args, by_rows)
    assert every.any() and not every.all()
    np.testing.assert_array_equal(by_rows, every)


@pytest.mark.parametrize("n_rays", [16, 64, 100])
@pytest.mark.parametrize("seed", range(8))
def test_flagging_by_cells_keeps_every_flagged_ray(seed, n_rays):
    """``_cells_meeting`` leaves out whole columns (azimuths) of a row, yet ``_flag_rows_kernel`` still gives
    ``_flag_kernel``'s flags: small and large moved spheres (5 to 30 cm), one to four of them, near and far,
    points inside the source's sphere (cosine-weighted rays about the normal) and outside, per-point grids."""
    from prtlab.interreflection._residual import NO_BOX, _cells_meeting, _flag_kernel, _flag_rows_kernel, _grid, _key

    rng = np.random.default_rng(100 + seed)
    n_points = 300
    points = rng.uniform(-3.0, 3.0, size=(n_points, 3))
    normals = rng.normal(size=(n_points, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    centre, radius = rng.uniform(-1.0, 1.0, 3), float(rng.uniform(0.2, 2.0))
    n_spheres = 1 + seed % 4
    spheres = np.concatenate([centre + rng.normal(scale=0.5 * radius, size=(n_spheres, 3)),  # about the source
                              10.0 ** rng.uniform(-1.3, -0.5, size=(n_spheres, 1))], axis=1)
    full = 0.5 if seed % 2 else 0.0
    rows, side = _grid(n_rays)
    args = (points, normals, np.arange(n_points), centre, radius, radius * 1.01, _key(seed, 2), rows, side, 1e-4,
            full, np.zeros(3), NO_BOX, spheres)
    every, by_cells = (np.empty((n_points, rows * side), np.bool_) for _ in range(2))
    _flag_kernel(*args, every)
    _flag_rows_kernel(*args, by_cells)
    np.testing.assert_array_equal(by_cells, every)
    assert every.any()
    need, band = np.empty(rows * side, np.bool_), np.empty(rows * side + 1)
    partial_rows = 0  # rows some of whose columns are needed and some not: the column test at work
    for p in range(n_points):
        rp, sp = _cells_meeting(points, normals, p, centre, radius, rows, side, 1e-4, full, spheres, need, band)
        cells = need[:rp * sp].reshape(rp, sp)
        partial_rows += int(np.count_nonzero(cells.any(axis=1) & ~cells.all(axis=1)))
    assert partial_rows > 0


@pytest.mark.parametrize("seps", [(LAMBERT, LAMBERT, LAMBERT), (LAMBERT, PHONG, PHONG)])
def test_near_hit_correction_kernel_equals_the_reference(seps):
    """``near_hit_correction``'s kernel equals its numpy tier at 1e-12 (K' = K = 1 and glossy K' = K = 3), on every
    hit and on a subset with repeated receiver points, and gives zeros with no hits."""
    from prtlab.interreflection._residual import near_hit_correction

    meshes, poses, _ = _objects()
    caster = RayCaster(meshes, transforms=poses)
    x, n = _receiver(meshes, poses, 0)
    hits = residual_hits(x, n, seps[0], caster, _sources(meshes, poses, [1, 2], seps), 64)
    rng = np.random.default_rng(4)
    for i, h in hits.items():
        values = rng.normal(size=(len(meshes[i].vertices), seps[i].K, 3))
        for index in (np.arange(len(h.rows)), np.sort(rng.choice(len(h.rows), size=len(h.rows) // 3, replace=False)),
                      np.zeros(0, np.int64)):
            exact = rng.normal(size=(len(index), seps[i].K, 3))
            ref = near_hit_correction(h, index, exact, values, len(x), method="reference")
            fast = near_hit_correction(h, index, exact, values, len(x))
            assert fast.shape == ref.shape
            np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-12 * max(np.abs(ref).max(initial=0.0), 1.0))


@pytest.mark.parametrize("seed", range(8))
def test_update_equals_merge_then_same(seed):
    """``_update`` (the kernels' merge of recast hits) gives what ``_merge`` then ``_same`` give: ``old`` itself
    when the recast rays hit as before, else the merged arrays, bit for bit; on random hit sets where the recast
    rays keep, change, gain or lose their hits."""
    from prtlab.interreflection._residual import ResidualHits, _merge, _same, _update

    rng = np.random.default_rng(seed)
    faces = np.zeros((5, 3), np.int64)

    def hits(rays):
        rays = np.sort(np.asarray(rays, np.int64))
        return ResidualHits(rays // 64, rng.normal(size=(len(rays), 1, 1)), rays, rng.integers(0, 5, len(rays)),
                            rng.random((len(rays), 2)), faces)

    old = hits(rng.choice(5000, size=600, replace=False))
    recast = np.sort(rng.choice(5000, size=200, replace=False)).astype(np.int64)
    again = np.isin(old.rays, recast)
    assert again.any()
    changed = ResidualHits(*(a[again].copy() for a in old.arrays()), faces)
    changed.factor[0] += 1.0
    cases = [ResidualHits(*(a[again] for a in old.arrays()), faces), None,
             hits(rng.choice(recast, size=50, replace=False)), changed]
    for new in cases:
        if new is not None and not len(new.rays):
            new = None
        merged = _merge(old, recast, new)
        expected = old if _same(merged, old) else merged
        got = _update(old, recast, new)
        assert (got is old) == (expected is old)
        assert (got is None) == (expected is None)
        if got is not None:
            for a, b in zip(got.arrays(), expected.arrays()):
                assert a.dtype == b.dtype
                np.testing.assert_array_equal(a, b)
    assert _update(None, recast, cases[2]) is cases[2]


def test_kept_blockers_equal_a_fresh_instances(low_ball):
    """``_blockers`` kept per pair (``FrameReuse.pair_blockers``; moved objects tested again) equals a fresh
    instance's at every pose of an object that moves from far off to between the ball and the floor and back."""
    from prtlab.interreflection import Interreflection
    from prtlab.pipeline import FrameState
    from prtlab.scene import SceneObject, Transform

    base = low_ball.scene
    other = SceneObject("other", base.object("ball").mesh, Transform(translate=np.array([3.0, 0.55, -3.0])),
                        base.object("ball").material)
    scene = type(base)(objects=[*base.objects, other], lights=base.lights, camera=base.camera)
    data = {**low_ball.data, "other": low_ball.data["ball"]}
    ir = Interreflection(scene, low_ball.options, data)
    lists = set()
    for where in ([3.0, 0.55, -3.0], [0.9, 0.3, 0.0], [0.9, 0.3, 0.0], [3.0, 0.55, -3.0]):
        state = FrameState.from_scene(scene)
        state.transforms["other"] = Transform(translate=np.array(where))
        geo, fresh = ir._frame_geometry(state), Interreflection(scene, low_ball.options, data)
        fresh_geo = fresh._frame_geometry(state)
        for r in ir.objects:
            for s in ir.objects:
                if r is not s:
                    kept = ir._blockers(geo, r, s)
                    assert kept == fresh._blockers(fresh_geo, r, s)
                    lists.add(tuple(kept))
    assert len(lists) > 1  # the moving object blocks some pair at one pose and not at another


@pytest.mark.parametrize("full", [0.0, 0.3])
@pytest.mark.parametrize("r", [0, 1, 2])
def test_packet_casts_equal_one_ray_casts(r, full, monkeypatch):
    """The cast kernels' packets of 16 rays (``rtcIntersect16``, ``_raycast.PACKETS``) give the arrays of one ray
    at a time (``rtcIntersect1``) bit for bit and count the same rays: a full cast (the ball a source of itself)
    and, after the box moves, the incremental cast."""
    from prtlab.geometry import _raycast

    runs = {}
    for packets in (True, False):
        monkeypatch.setattr(_raycast, "PACKETS", packets)
        runs[packets] = _casts_before_and_after_a_move((LAMBERT, PHONG, LAMBERT), r, full)
    _assert_same_casts(runs[False], runs[True])


@pytest.mark.parametrize("shape, density", [((0, 64), 0.5), ((3, 64), 0.0), ((200, 16), 0.05), ((50, 64), 1.0)])
def test_flagged_rays_are_numpys_nonzero(shape, density):
    """``_residual._flagged`` (the recast's flagged rays) gives ``np.nonzero``'s rows and columns, order and dtype,
    empty and full arrays included."""
    from prtlab.interreflection._residual import _flagged

    rng = np.random.default_rng(8)
    state = np.where(rng.random(shape) < density, rng.integers(1, 4, shape), 0).astype(np.int8)
    for ours, numpys in zip(_flagged(state), np.nonzero(state)):
        assert ours.dtype == numpys.dtype
        np.testing.assert_array_equal(ours, numpys)


def test_the_near_hit_correction_in_parallel_runs_equals_one_pass():
    """:func:`near_hit_correction` adds runs of hits with distinct receiver points in parallel: bit for bit the sum
    of one pass over the hits in order, within 1e-12 of the reference tier; unsorted rows take one pass."""
    from prtlab.interreflection import _residual
    from prtlab.interreflection._residual import ResidualHits, near_hit_correction

    rng = np.random.default_rng(12)
    n_hits, n_points, n_vertices = 30_000, 2_000, 50
    faces = rng.integers(0, n_vertices, (40, 3))
    rows = np.sort(rng.integers(0, n_points, n_hits))
    uv = rng.uniform(0.0, 0.5, (n_hits, 2))
    hits = ResidualHits(rows, rng.normal(size=(n_hits, 2, 3)), np.arange(n_hits), rng.integers(0, 40, n_hits), uv,
                        faces)
    index = np.sort(rng.choice(n_hits, 20_000, replace=False))
    exact, values = rng.normal(size=(len(index), 3, 3)), rng.normal(size=(n_vertices, 3, 3))
    assert len(_residual._row_runs(rows[index])) > 3
    ours = near_hit_correction(hits, index, exact, values, n_points)
    one = np.zeros_like(ours)
    _residual._near_correction_kernel(rows, hits.factor, hits.triangles, uv, faces, index, exact, values,
                                      np.array([0, len(index)]), one)
    np.testing.assert_array_equal(ours, one)
    ref = near_hit_correction(hits, index, exact, values, n_points, method="reference")
    np.testing.assert_allclose(ours, ref, rtol=0.0, atol=1e-12 * np.abs(ref).max())
    np.testing.assert_array_equal(_residual._row_runs(rows[index][::-1]), [0, len(index)])


def test_the_rgb_near_hit_correction_equals_the_general_run():
    """With ``K' = K = 1`` and 3 colours :func:`near_hit_correction` takes the unrolled run
    (``_near_correction_run_rgb``): bit for bit, zeros' signs included, the general run's sums over the same hits
    in the same order (``_near_correction_run``), on hits whose corrections are exactly zero too."""
    from prtlab.interreflection import _residual
    from prtlab.interreflection._residual import ResidualHits, near_hit_correction

    rng = np.random.default_rng(31)
    n_hits, n_points, n_vertices = 20_000, 3_000, 60
    faces = rng.integers(0, n_vertices, (50, 3))
    rows = np.sort(rng.integers(0, n_points, n_hits))
    uv = rng.uniform(0.0, 0.5, (n_hits, 2)).astype(np.float32).astype(np.float64)
    factor = rng.normal(size=(n_hits, 1, 1))
    factor[::7] = -0.0  # products -0.0 and 0.0: the sum's start 0.0 decides the zeros' signs
    hits = ResidualHits(rows, factor, np.arange(n_hits), rng.integers(0, 50, n_hits), uv, faces)
    index = np.sort(rng.choice(n_hits, 15_000, replace=False))
    exact, values = rng.normal(size=(len(index), 1, 3)), rng.normal(size=(n_vertices, 1, 3))
    ours = near_hit_correction(hits, index, exact, values, n_points)
    general = np.zeros_like(ours)
    _residual._near_correction_run(rows, factor, hits.triangles, uv, faces, index, exact, values, 0, len(index),
                                   general)
    assert len(_residual._row_runs(rows[index])) > 3
    assert np.any(ours == 0.0)
    np.testing.assert_array_equal(ours, general)
    np.testing.assert_array_equal(np.signbit(ours), np.signbit(general))


def test_light_outer_kernel_is_numpys_outer_and_sum():
    """``light_outer_kernel`` gives ``np.multiply.outer`` and then ``out + outer`` bit for bit."""
    from prtlab.interreflection._residual import light_outer_kernel

    rng = np.random.default_rng(4)
    first, second = rng.normal(size=(37, 2)), rng.normal(size=(37, 2))
    r1, r2 = rng.normal(size=3), rng.normal(size=3) * 1e3
    out = np.empty((37, 2, 3))
    light_outer_kernel(first, r1, out, False)
    assert np.array_equal(out, np.multiply.outer(first, r1))
    light_outer_kernel(second, r2, out, True)
    assert np.array_equal(out, np.multiply.outer(first, r1) + np.multiply.outer(second, r2))
