"""Tests of prtlab/interreflection/_fields.py: basis radiance of a source object."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prtlab import brdf
from prtlab.geometry import _embree, builtin_mesh
from prtlab.geometry._raycast import may_hit_ray
from prtlab.interreflection import basis_radiance_at, basis_radiance_field
from prtlab.scene import AreaLight
from prtlab.shadowfields import area_light_sh, sphere_grid

ORDER = 4
PLANE = builtin_mesh("plane", size=[2.0, 2.0], resolution=[4, 4])  # y = 0, normals +y
LAMBERT = brdf.separable(brdf.lambert(np.ones(3)), 1, resolution=(8, 16))
GLOSSY = brdf.separable(brdf.phong(0.3, 0.5, 8.0), 2, resolution=(8, 16))


def test_constant_basis_on_a_plane_is_the_sh_of_the_plane_seen_as_an_area_light(rng):
    """Psi = 1 on a flat source: S is the indicator of the directions that see its front side, which is
    what area_light_sh integrates over the light's area (an independent route, converged at 24 nodes).
    The ray-cast projection of the step converges to it at a step function's quadrature rate: each
    doubling of the degree (31, 63, 127) at least cuts the relative RMS over 20 points 0.5..2 above the
    plane to ``STEP_RATE`` of the previous one."""
    from tests.shadowfields.test_occlusion import STEP_RATE

    points = np.stack([rng.uniform(-1.5, 1.5, 20), rng.uniform(0.5, 2.0, 20), rng.uniform(-1.5, 1.5, 20)], axis=1)
    light = AreaLight(center=np.zeros(3), u=np.array([0.0, 0.0, 1.0]), v=np.array([1.0, 0.0, 0.0]),
                      radiance=np.ones(3))  # cross(u, v) = +y: the front side
    ref = area_light_sh(light, points, ORDER, n_nodes=24)[..., 0]
    rms = []
    for degree in (31, 63, 127):
        s = basis_radiance_at(PLANE, np.ones((1, len(PLANE.vertices))), LAMBERT, points, ORDER, degree=degree)
        assert s.shape == (20, 1, 1, 16)
        err = np.linalg.norm(s[:, 0, 0] - ref, axis=1) / np.linalg.norm(ref, axis=1)
        rms.append(np.sqrt(np.mean(err**2)))
    assert rms[1] <= STEP_RATE * rms[0] and rms[2] <= STEP_RATE * rms[1], rms
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


# --------------------------------------------------------------------------- self-interreflection


def _on_one_wall(v):
    """Vertices of the 2 x 2 x 2 room on exactly one wall (not on an edge or a corner)."""
    walls = (np.abs(v[:, 0]) > 0.999).astype(int) + (np.abs(v[:, 2]) > 0.999) + (v[:, 1] < 1e-3) + (v[:, 1] > 1.999)
    return walls == 1


def test_self_basis_irradiance_known_answers():
    """Inside a closed room (normals inward) a constant unit radiance fills every hemisphere:
    ``int 1 * g cos = 1`` for Lambert (g = 1/pi); a convex object sees none of itself."""
    from prtlab.geometry import shading_points
    from prtlab.interreflection import self_basis_irradiance

    room = builtin_mesh("room", size=[2.0, 2.0, 2.0], windows=[], cell_size=0.5)
    v = np.asarray(room.vertices)
    inner = _on_one_wall(v)
    pts = shading_points(room.vertices, room.faces, room.vertex_normals)[inner]
    psi = np.stack([np.ones(len(v)), 2.0 * np.ones(len(v))])
    phi = self_basis_irradiance(room, psi, LAMBERT, pts, room.vertex_normals[inner], degree=31)
    assert inner.sum() > 50 and phi.shape == (inner.sum(), 1, 1, 2)
    # every direction of the hemisphere hits the room: the rule's own sum of cos / pi, within 1 % of 1
    from prtlab import sh

    dirs, w = sh.quadrature(1, 31)
    rule = np.maximum(room.vertex_normals[inner] @ dirs.T, 0.0) @ w / np.pi
    np.testing.assert_allclose(phi[:, 0, 0, 0], rule, atol=1e-10)
    np.testing.assert_allclose(phi[:, 0, 0, 1], 2.0 * rule, atol=1e-10)
    np.testing.assert_allclose(rule, 1.0, rtol=0.01)
    ball = builtin_mesh("icosphere", subdivisions=2)
    none = self_basis_irradiance(ball, np.ones((1, len(ball.vertices))), LAMBERT, ball.vertices, ball.vertex_normals)
    np.testing.assert_array_equal(none, 0.0)
    with pytest.raises(ValueError, match="basis must be"):
        self_basis_irradiance(ball, np.ones((1, 3)), LAMBERT, ball.vertices, ball.vertex_normals)
    with pytest.raises(ValueError, match="points and normals must both be"):
        self_basis_irradiance(ball, np.ones((1, len(ball.vertices))), LAMBERT, ball.vertices, np.zeros((2, 3)))
    assert self_basis_irradiance(ball, np.ones((1, len(ball.vertices))), LAMBERT, np.zeros((0, 3)),
                                 np.zeros((0, 3))).shape == (0, 1, 1, 1)


def test_self_basis_irradiance_against_monte_carlo():
    """One bounce of an object on itself: the weights of hat functions (Psi = identity, so the basis adds
    no error) are the vertex radiance of the Monte Carlo direct light, and the irradiance they give a
    vertex inside the open box (floor + 3 walls of the room mesh, lit through the missing wall) equals the
    reference's one-bounce light there within its standard error plus the piecewise-linear-radiance bound."""
    from prtlab.geometry import shading_points
    from prtlab.interreflection import self_basis_irradiance
    from prtlab.reference import path_trace
    from prtlab.scene import EnvironmentLight, Material, Scene, SceneObject
    from tests.conftest import MC_SIGMAS

    room = builtin_mesh("room", size=[2.0, 2.0, 2.0], windows=[], cell_size=0.5)
    v = np.asarray(room.vertices)
    keep_faces = ~np.all(v[room.faces][:, :, 2] > 0.999, axis=1) & ~np.all(v[room.faces][:, :, 1] > 1.999, axis=1)
    import trimesh

    box = trimesh.Trimesh(v, room.faces[keep_faces], vertex_normals=room.vertex_normals, process=False)
    sky = EnvironmentLight(constant=np.ones(3))
    scene = Scene(objects=[SceneObject("box", box, material=Material("diffuse", np.full(3, 0.6)))], lights=[sky])
    ref = path_trace(scene, 1, 256, np.random.default_rng(3))
    used = np.unique(box.faces)
    inner = np.zeros(len(v), bool)
    inner[used] = _on_one_wall(v[used])
    pts = shading_points(box.vertices, box.faces, box.vertex_normals)[inner]
    phi = self_basis_irradiance(box, np.eye(len(v)), LAMBERT, pts, box.vertex_normals[inner], degree=63)
    ours = 0.6 * phi[:, 0, 0, :] @ ref.direct["box"][:, 0]  # albedo * sum_i Phi_i L_i
    truth, se = ref.indirect["box"][inner, 0], ref.stderr["indirect"]["box"][inner, 0]
    # piecewise-linear vertex radiance on a 0.5 grid vs the exact radiance: 5 % of the value
    assert truth.mean() > 0.05 and np.all(np.abs(ours - truth) <= MC_SIGMAS * se + 0.05 * truth), np.c_[ours, truth, se]


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_points=st.integers(0, 6), glossy=st.booleans())
def test_projection_over_the_hits_equals_the_dense_reference_tier(seed, n_points, glossy):
    """The numba tier (hit kernel, hit-only projection, a Lambertian source's constant ``h``) and the dense
    float64 specification agree on a closed mesh seen from inside and outside (some rays miss, some are
    culled by the bounding sphere), for a glossy (K = 2) and a Lambertian source."""
    rng = np.random.default_rng(seed)
    mesh = builtin_mesh("icosphere", subdivisions=1)
    psi = rng.normal(size=(3, len(mesh.vertices)))
    points = rng.normal(size=(n_points, 3)) * rng.uniform(0.3, 3.0, size=(n_points, 1))
    sep = GLOSSY if glossy else LAMBERT
    fast = basis_radiance_at(mesh, psi, sep, points, ORDER, degree=15)
    ref = basis_radiance_at(mesh, psi, sep, points, ORDER, degree=15, method="reference")
    assert fast.shape == (n_points, sep.K, 3, 16)
    np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="method must be 'numba' or 'reference'"):
        basis_radiance_at(mesh, psi, GLOSSY, points, ORDER, method="gpu")


@pytest.mark.parametrize("packets", [True, False])
@pytest.mark.parametrize("mesh", ["plane", "sphere"])
def test_fused_source_hits_equal_the_casters(rng, mesh, packets):
    """``source_hits``'s fused kernel (the bounding test and the trace in one pass, packets of 16 rays or one ray
    at a time) gives the candidate rays, faces and barycentrics of ``RayCaster.may_hit`` then ``closest_hit``,
    bit for bit, batch by batch (points around the source, inside its bounds too)."""
    from prtlab import sh
    from prtlab.geometry import RayCaster, _raycast
    from prtlab.interreflection._fields import source_hits

    source = PLANE if mesh == "plane" else builtin_mesh("icosphere")
    caster = RayCaster([(np.asarray(source.vertices, float), np.asarray(source.faces))])
    points = rng.normal(size=(150, 3)) * 1.2
    dirs, _ = sh.quadrature(ORDER, 31)
    default = _raycast.PACKETS
    try:
        _raycast.PACKETS = packets
        fused = list(source_hits(caster, points, dirs, 37))
    finally:
        _raycast.PACKETS = default
    reference = list(source_hits(caster, points, dirs, 37, method="reference"))
    assert len(fused) == len(reference) > 1
    for (a, b, point, direction, hits, at), ref in zip(fused, reference):
        assert (a, b) == ref[:2]
        np.testing.assert_array_equal(point[at], ref[2][ref[5]])
        np.testing.assert_array_equal(direction[at], ref[3][ref[5]])
        np.testing.assert_array_equal(hits.triangle[at], ref[4].triangle[ref[5]])
        np.testing.assert_array_equal(hits.barycentric[at], ref[4].barycentric[ref[5]])


@numba.njit(parallel=True, nogil=True)
def _source_hits_by_point(tracer, origins, dirs, centre, r2, lo, hi, tnear, triangle, uv):
    """``source_hits_kernel`` as it was before its tasks took 16 origins: a task takes one origin (its slot) and
    fills a packet with 16 of that origin's rays in the order of ``j``."""
    n_points, n_dirs = origins.shape[0], dirs.shape[0]
    w = _embree.PACKET
    counter = np.zeros(1, dtype=np.int64)
    for _ in numba.prange(tracer.threads):
        lanes = np.empty(w, np.int64)
        while True:
            p = _embree.fetch_add(counter, 1)
            if p >= n_points:
                break
            f32, u32 = tracer.slot_f32[p], tracer.slot_u32[p]
            valid = tracer.valid[p]
            ox, oy, oz = origins[p, 0], origins[p, 1], origins[p, 2]
            cx, cy, cz = centre[0] - ox, centre[1] - oy, centre[2] - oz
            dist2 = cx * cx + cy * cy + cz * cz
            n_lanes = 0
            for j in range(n_dirs + 1):
                if j < n_dirs:
                    triangle[p, j] = -1
                    dx, dy, dz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
                    if not may_hit_ray(ox, oy, oz, cx, cy, cz, dist2, r2, dx, dy, dz, lo, hi):
                        continue
                    length = np.sqrt(dx * dx + dy * dy + dz * dz)
                    dx /= length
                    dy /= length
                    dz /= length
                    if not tracer.packet:
                        _embree.set_ray(f32, u32, ox + tnear * dx, oy + tnear * dy, oz + tnear * dz, dx, dy, dz,
                                        np.inf)
                        _embree.rtc_call(tracer.function, tracer.scene, f32.ctypes.data)
                        if u32[_embree.HIT_GEOM] != _embree.INVALID_ID:
                            triangle[p, j] = np.int32(u32[_embree.HIT_PRIM])
                            uv[p, j, 0] = f32[_embree.HIT_U]
                            uv[p, j, 1] = f32[_embree.HIT_V]
                        continue
                    _embree.set_packet_ray(f32, u32, n_lanes, ox + tnear * dx, oy + tnear * dy, oz + tnear * dz,
                                           dx, dy, dz, np.inf)
                    valid[n_lanes] = -1
                    lanes[n_lanes] = j
                    n_lanes += 1
                    if n_lanes < w:
                        continue
                if n_lanes == 0:
                    continue
                for k in range(n_lanes, w):
                    valid[k] = 0
                _embree.rtc_call_packet(tracer.function, valid.ctypes.data, tracer.scene, f32.ctypes.data)
                for k in range(n_lanes):
                    if u32[_embree.HIT_GEOM * w + k] != _embree.INVALID_ID:
                        triangle[p, lanes[k]] = np.int32(u32[_embree.HIT_PRIM * w + k])
                        uv[p, lanes[k], 0] = f32[_embree.HIT_U * w + k]
                        uv[p, lanes[k], 1] = f32[_embree.HIT_V * w + k]
                n_lanes = 0


def _hit_origins(rng, mesh, where, n):
    """``n`` origins about the source (``"plane"``: y = 0, half size 1; ``"sphere"``: the unit icosphere): a small
    icosphere's vertices (neighbouring origins) above, below or beside it, or scattered points around and in it."""
    if where == "scattered":
        return rng.normal(size=(n, 3)) * 1.2
    ball = np.asarray(builtin_mesh("icosphere", subdivisions=2).vertices, float)[:n]
    offset = {"above": [0.2, 0.35, -0.1], "below": [-0.3, -0.32, 0.4], "beside": [1.6, 0.05, 0.2]}[where]
    if mesh == "sphere":
        offset = np.array(offset) * [1.0, 4.0, 1.0]
    return 0.3 * ball + offset


@pytest.mark.parametrize("where", ["above", "below", "beside", "scattered"])
@pytest.mark.parametrize("mesh", ["plane", "sphere"])
def test_source_hits_kernel_equals_the_former_kernel_and_one_ray(rng, mesh, where):
    """``source_hits_kernel`` (16 origins a task, ray ``j`` of each in a packet's lanes) gives the faces and
    barycentrics of the former kernel (one origin a task, 16 of its rays a packet) and of one ray at a time, bit
    for bit, for every ray (P not a multiple of 16, origins above, below and beside the source and about it)."""
    from prtlab import sh
    from prtlab.geometry import RayCaster, _raycast
    from prtlab.interreflection import _kernels
    from prtlab.interreflection._residual import _tracer

    source = PLANE if mesh == "plane" else builtin_mesh("icosphere")
    caster = RayCaster([(np.asarray(source.vertices, float), np.asarray(source.faces))])
    origins = np.ascontiguousarray(_hit_origins(rng, mesh, where, 157))
    dirs, _ = sh.quadrature(ORDER, 23)
    dirs = np.ascontiguousarray(dirs, dtype=np.float64)
    centre, radius, lo, hi = caster.may_hit_bounds()
    bounds = (np.asarray(centre, np.float64), float(radius) ** 2, lo, hi, float(caster.tnear))
    results = {}
    default = _raycast.PACKETS
    try:
        for packets in (True, False):
            _raycast.PACKETS = packets
            for name, kernel, n_tasks in (("new", _kernels.source_hits_kernel, _kernels.source_hit_tasks(157)),
                                          ("former", _source_hits_by_point, 157)):
                triangle = np.full((157, len(dirs)), 7, np.int32)
                uv = np.full((157, len(dirs), 2), np.nan, np.float32)
                kernel(_tracer(caster, n_tasks), origins, dirs, *bounds, triangle, uv)
                results[name, packets] = triangle, uv
    finally:
        _raycast.PACKETS = default
    triangle, uv = results["former", True]
    hit = triangle >= 0
    assert hit.any() and (~hit).any()
    for key, (t, u) in results.items():
        np.testing.assert_array_equal(t, triangle, err_msg=str(key))
        np.testing.assert_array_equal(u[hit], uv[hit], err_msg=str(key))
        assert u[hit].view(np.uint32).tolist() == uv[hit].view(np.uint32).tolist()


def test_may_hit_group_equals_may_hit_ray(rng):
    """``_may_hit_group`` (16 origins side by side, no branches) gives ``may_hit_ray``'s test of each ray: random
    and axis-aligned directions, origins inside, outside and on the faces of the box, inside and outside the
    sphere."""
    from prtlab.interreflection._kernels import _may_hit_group

    lo, hi = np.array([-1.0, -1e-6, -0.5]), np.array([1.0, 1e-6, 0.75])
    centre, r2 = np.array([0.0, 0.0, 0.1]), 1.3**2
    origins = rng.normal(size=(16 * 20, 3)) * 1.5
    origins[::5] = np.where(rng.random((len(origins[::5]), 3)) < 0.5, lo, hi)  # corners of the box
    origins[1::5, 1] = 0.0
    dirs = np.concatenate([rng.normal(size=(40, 3)), np.eye(3), -np.eye(3), [[1.0, 1.0, 0.0], [0.0, -1.0, 1.0]]])
    for group in origins.reshape(-1, 16, 3):
        rows = np.zeros((7, 16))
        rows[:3] = group.T
        rows[3:6] = (centre - group).T
        rows[6] = np.sum((centre - group) ** 2, axis=1)
        for n in (16, 11):
            for d in dirs:
                got = np.zeros(16, bool)
                _may_hit_group(rows, n, r2, d[0], d[1], d[2], lo, hi, got)
                want = [may_hit_ray(*o, *c, c2, r2, *d, lo, hi) for o, c, c2 in zip(group, rows[3:6].T, rows[6])]
                np.testing.assert_array_equal(got[:n], want[:n])


@pytest.mark.parametrize("packets", [True, False])
@pytest.mark.parametrize("mesh", ["plane", "sphere"])
def test_fused_projection_equals_the_hit_kernels(rng, mesh, packets):
    """The fused hit radiance and projection (``project_source_hits_kernel``, a constant ``h``) gives the sums of
    the hit kernels over ``source_hits``' hits (``hit_basis_kernel``, ``project_hits_kernel``) bit for bit, over
    several batches (points around the source, inside its bounds too, some with no hit)."""
    from prtlab import sh
    from prtlab.geometry import RayCaster, _raycast
    from prtlab.interreflection import _fields

    source = PLANE if mesh == "plane" else builtin_mesh("icosphere")
    vertices, faces = np.asarray(source.vertices, float), np.asarray(source.faces, dtype=np.int64)
    normals = np.asarray(source.vertex_normals, dtype=np.float64)
    caster = RayCaster([(vertices, faces)])
    points = rng.normal(size=(150, 3)) * 1.2
    psi = rng.normal(size=(3, len(vertices)))
    dirs, weights = sh.quadrature(ORDER, 31)
    wy = weights[:, None] * sh.basis(dirs, ORDER)
    h = LAMBERT.h(np.array([0.0, 0.0, 1.0]))
    fused, kernels = np.zeros((2, len(points), 3, ORDER * ORDER))
    default, batch = _raycast.PACKETS, _fields._RAYS_PER_BATCH
    try:
        _raycast.PACKETS = packets
        _fields._RAYS_PER_BATCH = 37 * len(dirs)  # batches of 37 points
        _fields._projected_hits_fused(caster, points, dirs, wy, faces, normals, psi, np.broadcast_to(h, (1,)), fused)
        _fields._projected_hits(caster, points, dirs, wy, faces, normals, psi, LAMBERT, 37, "numba", kernels)
    finally:
        _raycast.PACKETS, _fields._RAYS_PER_BATCH = default, batch
    assert np.count_nonzero(fused) and np.count_nonzero(~fused.any(axis=(1, 2)))
    np.testing.assert_array_equal(fused, kernels)


@pytest.mark.parametrize("n_b, n_k, n2", [(16, 1, 16), (5, 2, 16), (16, 3, 9), (7, 1, 25), (3, 2, 1)])
def test_projection_kernel_equals_its_reference_bit_for_bit(rng, n_b, n_k, n2):
    """``project_source_hits_kernel`` (scratch rows, blocks of hits, register tiles at ``n2 = 16``) gives the bits
    of ``project_source_hits_reference`` (each term added into ``out`` in ray order) on random hits: more
    front hits a point than ``HIT_BLOCK``, counts not a multiple of the tile, back faces, points without
    hits, zero ``h_k`` and zero ``Psi`` at some vertices (their terms skipped, in some blocks only) and any
    values, signed zeros included, in ``out`` on entry."""
    from prtlab.interreflection import _kernels

    n_points, n_dirs, n_vertices, n_faces = 23, 300, 40, 60
    faces = rng.integers(0, n_vertices, size=(n_faces, 3)).astype(np.int64)
    normals = rng.normal(size=(n_vertices, 3))
    dirs = rng.normal(size=(n_dirs, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    triangle = np.where(rng.random((n_points, n_dirs)) < rng.random((n_points, 1)),
                        rng.integers(0, n_faces, size=(n_points, n_dirs)), -1).astype(np.int32)
    triangle[:3] = -1  # no hit
    triangle[3, 150:] = -1
    triangle[4, 200:] = -1
    uv = rng.dirichlet(np.ones(3), size=(n_points, n_dirs))[..., :2].astype(np.float32)
    basis_t = rng.normal(size=(n_vertices, n_b))
    basis_t[rng.random((n_vertices, n_b)) < 0.02] = 0.0  # Psi = 0 where the three corners are 0
    basis_t[:8, 0] = 0.0
    faces[:5] = [0, 1, 2]
    h = rng.uniform(0.5, 2.0, n_k)
    if n_k > 1:
        h[1] = 0.0
    wy = rng.normal(size=(n_dirs, n2))
    out = rng.normal(size=(n_points, n_k * n_b, n2))
    out[::2, ::3] = -0.0
    out[1::2, 1::3] = 0.0
    ref = out.copy()
    _kernels.project_source_hits_reference(triangle, uv, faces, normals, basis_t, h, dirs, wy, ref)
    _kernels.project_source_hits_kernel(triangle, uv, faces, normals, basis_t, h, dirs, wy, out)
    front = (triangle >= 0).sum(axis=1)
    assert front.max() > 2 * _kernels.HIT_BLOCK and np.any(ref != out.copy() * 0)  # many hits, some terms
    np.testing.assert_array_equal(out.view(np.int64), ref.view(np.int64))


def _tilted_flat_mesh(rng):
    """A flat mesh off the axes: a 6 x 5 plane grid with its inner vertices moved in the plane (faces of
    different shapes), rotated and moved."""
    import trimesh

    from tests.conftest import random_rotation

    grid = builtin_mesh("plane", size=[2.0, 1.6], resolution=[6, 5])
    v = np.array(grid.vertices, float)
    inner = (np.abs(v[:, 0]) < 0.99) & (np.abs(v[:, 2]) < 0.79)
    v[inner, 0] += rng.uniform(-0.08, 0.08, inner.sum())
    v[inner, 2] += rng.uniform(-0.06, 0.06, inner.sum())
    v = v @ random_rotation(rng).T + [0.3, -0.2, 0.5]
    return trimesh.Trimesh(v, np.asarray(grid.faces), process=False)


def _flat_mesh(rng, mesh):
    return PLANE if mesh == "plane" else _tilted_flat_mesh(rng)


def _flat_points(rng, source, n):
    """Points about a flat source in its own frame: above and below it, on its plane, near its edges, far."""
    v = np.asarray(source.vertices, float)
    a, b, c = v[source.faces[0]]
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal)
    centre = v.mean(axis=0)
    spread = np.ptp(v, axis=0)
    points = centre + rng.uniform(-0.7, 0.7, size=(n, 3)) * spread  # in-plane positions, some beyond the edges
    points -= np.outer((points - centre) @ normal, normal)  # on the plane
    height = rng.choice([0.0, 1e-9, 0.02, 0.3, 1.0, -0.3], size=n)
    return points + height[:, None] * normal


def _flat_eps(source, origins, dirs, tnear):
    """(P, D): the barycentric bound of ``flat_source_hits_kernel`` at each ray (its docstring), from the mesh."""
    from prtlab.interreflection._kernels import FLAT_ROUNDING

    v, f = np.asarray(source.vertices, float), np.asarray(source.faces)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cross, axis=1)
    longest = np.max([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1)],
                     axis=0)
    normal = cross[0] / area2[0]
    u = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    o = origins[:, None, :] + tnear * u[None]  # (P, D, 3)
    cos = np.abs(u @ normal)[None]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.abs(((o - a[0]) @ normal) / (u @ normal)[None])
        return FLAT_ROUNDING * (np.abs(o).max(axis=2) + t + np.abs(v).max()) / (cos * np.min(area2 / longest))


def _front(source, triangle, uv, dirs):
    """(P, D) bool: the rays whose hit adds a term (``project_source_hits_reference``'s front test)."""
    faces, normals = np.asarray(source.faces), np.asarray(source.vertex_normals, float)
    t = np.maximum(triangle, 0)
    b1, b2 = uv[..., 0].astype(np.float64), uv[..., 1].astype(np.float64)
    n = ((1.0 - b1 - b2)[..., None] * normals[faces[t, 0]] + b1[..., None] * normals[faces[t, 1]]
         + b2[..., None] * normals[faces[t, 2]])
    return (triangle >= 0) & (np.sum(n * dirs[None], axis=2) < 0.0)


@pytest.mark.parametrize("mesh", ["plane", "tilted"])
def test_flat_source_hits_are_embrees_faces(rng, mesh):
    """``flat_source_hits_kernel`` (its undecided rays traced) gives Embree's face (``source_hits_kernel``) at every
    ray whose hit adds a term (a front hit), a face only where Embree hits it, barycentrics within the kernel's
    bound ``eps`` of Embree's (or Embree's bits) and Embree's bits at a face without a term (traced): points
    above, below and on the plane, beyond its edges; a regular and an irregular tilted mesh."""
    from prtlab import sh
    from prtlab.geometry import RayCaster
    from prtlab.interreflection import _fields, _kernels
    from prtlab.interreflection._residual import _tracer

    source = _flat_mesh(rng, mesh)
    vertices, faces = np.asarray(source.vertices, float), np.asarray(source.faces)
    caster = RayCaster([(vertices, faces)])
    plane = _fields.flat_source(vertices, faces, source.vertex_normals)
    assert plane is not None
    origins = np.ascontiguousarray(_flat_points(rng, source, 157))
    dirs = np.ascontiguousarray(sh.quadrature(ORDER, 31)[0], dtype=np.float64)
    centre, radius, lo, hi = caster.may_hit_bounds()
    bounds = (np.asarray(centre, np.float64), float(radius) ** 2, lo, hi, float(caster.tnear))
    embree = np.empty((157, len(dirs)), np.int32), np.full((157, len(dirs), 2), np.nan, np.float32)
    _kernels.source_hits_kernel(_tracer(caster, _kernels.source_hit_tasks(157)), origins, dirs, *bounds, *embree)
    triangle, uv = np.full((157, len(dirs)), 7, np.int32), np.full((157, len(dirs), 2), np.nan, np.float32)
    n_tasks = _kernels.source_hit_tasks(157)
    traced = _kernels.flat_source_hits_kernel(plane, _fields._ray_tracer(caster, n_tasks), origins, dirs, *bounds,
                                              triangle, uv)
    assert 0 < traced and np.count_nonzero(triangle >= 0) > 1000
    front = _front(source, *embree, dirs)
    assert front.any() and (~front).any()
    np.testing.assert_array_equal(triangle[front], embree[0][front])  # every term's face
    faced = triangle >= 0
    np.testing.assert_array_equal(triangle[faced], embree[0][faced])  # a face only where Embree hits it
    same = np.all(uv[faced].view(np.uint32) == embree[1][faced].view(np.uint32), axis=1)
    assert np.all(same[~front[faced]])  # a face without a term only where traced: Embree's bits
    gap = np.abs(uv[faced].astype(np.float64) - embree[1][faced]).max(axis=1)
    assert np.all(same | (gap <= _flat_eps(source, origins, dirs, caster.tnear)[faced]))


@pytest.mark.parametrize("mesh", ["plane", "tilted"])
def test_flat_source_radiance_is_the_reference_within_float32_barycentrics(rng, mesh):
    """``basis_radiance_at``'s numba tier on a flat source (hits located on its plane) is the float64 reference
    tier (Embree's hits) within the sum over each point's front hits of ``|h| |wy_j| 4 eps_j max|Psi|`` (a
    barycentric off by ``eps`` moves ``Psi`` by at most ``2 eps`` times twice its largest value) plus the sums'
    rounding."""
    from prtlab import sh
    from prtlab.geometry import RayCaster
    from prtlab.interreflection import _fields

    source = _flat_mesh(rng, mesh)
    vertices, faces = np.asarray(source.vertices, float), np.asarray(source.faces)
    assert _fields.flat_source(vertices, faces, source.vertex_normals) is not None
    psi = rng.normal(size=(3, len(vertices)))
    points = _flat_points(rng, source, 60)
    fast = basis_radiance_at(source, psi, LAMBERT, points, ORDER, degree=31)
    ref = basis_radiance_at(source, psi, LAMBERT, points, ORDER, degree=31, method="reference")
    caster = RayCaster([(vertices, faces)])
    dirs, weights = sh.quadrature(ORDER, 31)
    wy = weights[:, None] * sh.basis(dirs, ORDER)
    hits = caster.closest_hit(np.repeat(points, len(dirs), axis=0), np.tile(dirs, (len(points), 1)))
    triangle = np.where(hits.hit & caster.may_hit(points, dirs).ravel(), hits.triangle, -1).reshape(len(points), -1)
    front = _front(source, triangle, hits.barycentric.reshape(len(points), len(dirs), 2), dirs)
    eps = np.where(front, _flat_eps(source, points, dirs, caster.tnear), 0.0)
    h = float(np.abs(LAMBERT.h(np.array([0.0, 0.0, 1.0]))).max())
    bound = (4.0 * h * np.abs(psi).max() * eps) @ np.abs(wy)  # (P, n2)
    assert np.all(np.abs(fast - ref) <= bound[:, None, None, :] + 1e-12 * (1.0 + np.abs(ref)))
    assert np.abs(ref).max() > 0.1


def test_flat_source_of_a_mesh_that_is_not_flat_is_none(rng):
    """``flat_source`` declines a curved mesh, a flat one whose vertex normals disagree, and no faces."""
    from prtlab.interreflection._fields import flat_source

    ball = builtin_mesh("icosphere")
    assert flat_source(ball.vertices, ball.faces, ball.vertex_normals) is None
    normals = np.array(PLANE.vertex_normals)
    normals[::2] *= -1.0
    assert flat_source(PLANE.vertices, PLANE.faces, normals) is None
    assert flat_source(PLANE.vertices, np.zeros((0, 3), np.int64), PLANE.vertex_normals) is None
    assert flat_source(PLANE.vertices, PLANE.faces, PLANE.vertex_normals) is not None
