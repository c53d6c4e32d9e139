"""Tests of prtlab.spherelights._meshdirect (the objects' direct light against the real meshes, option
``mesh_blockers``)."""

import copy
import dataclasses

import numpy as np
import pytest

from prtlab import sh
from prtlab.geometry import RayCaster, builtin_mesh
from prtlab.pipeline import FrameState
from prtlab.scene import Scene
from prtlab.spherelights import SphereLights
from prtlab.spherelights._meshdirect import (MeshOccluder, fibonacci_directions, inner_spheres, mesh_direct,
                                             mesh_direct_visible, mesh_occluder, self_blocked)

WHITE = np.zeros((16, 3))
WHITE[0] = np.sqrt(4 * np.pi)  # constant radiance 1


def _ball(centre, radius=0.5, subdivisions=3):
    m = builtin_mesh(name="icosphere", radius=radius, subdivisions=subdivisions)
    return np.asarray(m.vertices) + np.asarray(centre, dtype=np.float64), np.asarray(m.faces)


def _no_bits(p, m):
    return np.zeros((len(p), (m + 7) // 8), dtype=np.uint8)


def _env(rng, order=4):
    env = 0.2 * rng.normal(size=(order * order, 3))
    env[0] += 3.0
    return env


# ------------------------------------------------------------------ known answers


def test_fibonacci_directions_are_unit_and_balanced():
    d = fibonacci_directions(2048)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(d.mean(axis=0), 0.0, atol=1e-3)
    assert not d.flags.writeable


def test_nothing_blocked_is_the_sh_irradiance(rng):
    p = rng.normal(size=(20, 3))
    n = rng.normal(size=(20, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    env = _env(rng)
    d = fibonacci_directions(512)
    e = mesh_direct(p, n, env, np.eye(3), _no_bits(p, 512), dirs=d)
    np.testing.assert_allclose(e, sh.basis(n, 4) @ sh.irradiance(env), rtol=1e-12)


@pytest.mark.parametrize("as_mesh", [False, True])
def test_ball_above_a_point_is_the_closed_form(as_mesh):
    """A ball of angular radius alpha straight above a point under a constant sky hides pi sin^2 alpha."""
    centre, radius = np.array([0.0, 2.0, 0.0]), 0.8
    p, n = np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]])
    d = fibonacci_directions(16384)
    if as_mesh:
        v, f = _ball([0.0, 0.0, 0.0], radius, subdivisions=5)
        occ = [mesh_occluder(v, f, translate=centre, bounds=np.append(centre, 1.001 * radius)[None])]
        e = mesh_direct(p, n, WHITE, np.eye(3), _no_bits(p, len(d)), occ, dirs=d)
    else:
        e = mesh_direct(p, n, WHITE, np.eye(3), _no_bits(p, len(d)), spheres=np.append(centre, radius)[None], dirs=d)
    sin2 = (radius / 2.0) ** 2
    np.testing.assert_allclose(e, np.pi * (1.0 - sin2), rtol=3e-3)


def test_a_ground_hides_the_lower_hemisphere():
    """A point on a vertical wall beside a huge ground: the ground hides the lower half, pi / 2 of pi."""
    p, n = np.array([[0.0, 1e-9, 0.0]]), np.array([[1.0, 0.0, 0.0]])
    rect = np.array([[0.0, 0.0, 0.0, 1e6, 0.0, 0.0, 1e6]])
    d = fibonacci_directions(4096)
    e = mesh_direct(p, n, WHITE, np.eye(3), _no_bits(p, len(d)), rectangles=rect, dirs=d)
    np.testing.assert_allclose(e, np.pi / 2, rtol=2e-3)


def test_self_blocked_inside_a_closed_mesh_is_everything():
    v, f = _ball([0.0, 0.0, 0.0], 1.0)
    d = fibonacci_directions(256)
    p = np.array([[0.0, 0.0, 0.0], [0.0, 5.0, 0.0]])
    n = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    bits = np.unpackbits(self_blocked(p, n, v, f, d), axis=1, count=len(d)).astype(bool)
    front = d[:, 1] > 0
    assert bits[0, front].all() and not bits[0, ~front].any() and not bits[1].any()


def test_inner_spheres_lie_inside_the_mesh(rng):
    """About a centre inside a ball's icosphere: a ball of about its inradius, whose points all lie inside (the first
    face met from each faces away); a centre outside is left out."""
    v, f = _ball([0.0, 0.0, 0.0], 0.5)
    inner = inner_spheres(v, f, [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [2.0, 0.0, 0.0]])
    assert inner.shape == (2, 4)
    assert 0.48 < inner[0, 3] < 0.5 and 0.38 < inner[1, 3] < 0.4
    x = rng.normal(size=(200, 3))
    x = inner[1, :3] + inner[1, 3] * rng.random((200, 1)) ** (1 / 3) * x / np.linalg.norm(x, axis=1, keepdims=True)
    hits = RayCaster([(v, f)]).closest_hit(x, np.broadcast_to([0.0, 0.0, 1.0], x.shape))
    assert hits.hit.all() and (hits.normal[:, 2] > 0).all()


# ------------------------------------------------------------------ tiers


def _random_case(rng):
    p = rng.uniform(-1.0, 1.0, size=(300, 3)) + [0.0, 0.5, 0.0]
    n = rng.normal(size=p.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = fibonacci_directions(256)
    bits = np.packbits(rng.random((len(p), len(d))) < 0.2, axis=1)
    v, f = _ball([0.0, 0.0, 0.0], 0.4)
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rot *= np.sign(np.linalg.det(rot))
    occ = [mesh_occluder(v, f, rot, 1.3, [0.8, 1.2, -0.3]), mesh_occluder(v, f, None, 0.7, [-1.5, 0.4, 0.6])]
    rect = np.array([[-0.2, 0.1, 0.0, 2.0, 0.5, -0.5, 2.0]])
    balls = np.array([[0.3, 2.0, 1.0, 0.3]])
    return p, n, d, bits, occ, rect, balls, rot


def test_kernels_match_the_reference(rng):
    p, n, d, bits, occ, rect, balls, rot = _random_case(rng)
    env = _env(rng)
    args = (p, n, env, rot, bits, occ, rect, balls, d)
    fast = mesh_direct(*args)
    ref = mesh_direct(*args, method="reference")
    np.testing.assert_allclose(fast, ref, rtol=1e-10, atol=1e-10)
    blocked = mesh_direct(p, n, env, rot, _no_bits(p, len(d)), dirs=d) - ref
    assert np.abs(blocked).max() > 0.1  # the case blocks something


def test_visible_kernel_matches_the_reference_at_the_ground_plane():
    """The kernel's rectangle test against the reference's bit for bit where its sign shortcut decides: receivers on
    the rectangle's plane (``+-0`` height), just above and below it, rays parallel to it (``d_y = +-0``), steep and
    grazing rays, receivers over and off the rectangle, with and without an opaque ball."""
    y0 = 0.25
    xs = np.array([-2.5, -0.3, 0.0, 0.7, 2.5])
    hs = np.array([0.0, -0.0, 1e-300, -1e-300, 1e-12, -1e-12, 0.3, -0.3])
    p = np.array([[x, y0 + h, 0.2 * x] for x in xs for h in hs])
    p[len(hs) * 2 + 1, 1] = y0  # exactly on the plane through the arithmetic too
    n = np.array([[0.3 * np.sin(k), np.cos(k), 0.2] for k in range(len(p))])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[::3] = [0.0, 1.0, 0.0]
    n[1::3] = [0.0, -1.0, 0.0]
    d = list(fibonacci_directions(64))
    for phi in np.linspace(0.0, 2.0 * np.pi, 9)[:-1]:
        for dy in (0.0, -0.0, 1e-300, -1e-300, 1e-9, -1e-9, 0.5, -0.5):
            s = np.sqrt(1.0 - dy * dy)
            d.append([s * np.cos(phi), dy, s * np.sin(phi)])
    d = np.array(d)
    rect = np.array([[y0, 0.1, -0.2, 2.0, 0.5, -0.5, 2.0]])
    none = np.zeros((len(p), (len(d) + 7) // 8), dtype=np.uint8)
    for balls in (None, np.array([[0.3, 2.0, 1.0, 0.3]])):
        fast = mesh_direct_visible(p, n, np.eye(3), none, rectangles=rect, spheres=balls, dirs=d)
        with np.errstate(invalid="ignore"):  # the reference's 0 * inf along rays parallel to the plane
            ref = mesh_direct_visible(p, n, np.eye(3), none, rectangles=rect, spheres=balls, dirs=d,
                                      method="reference")
        assert np.array_equal(fast, ref)
    below = np.unpackbits(fast, axis=1, count=len(d)).astype(bool)
    assert (~below).sum() > 0 and below.sum() > 0  # the rectangle hides some rays and not others


def test_meets_on_a_fibonacci_run_matches_every_direction(rng):
    """``_meets`` testing only the run of a turned Fibonacci set around the cones lists the same rays, in the same
    order, and clears the same ones as testing every direction (points near, inside and far from the spheres)."""
    from prtlab.spherelights._meshdirect import _meets

    d = fibonacci_directions(1024)
    for _ in range(4):
        rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        rot *= np.sign(np.linalg.det(rot))
        w = np.ascontiguousarray(d @ rot.T)
        p = rng.uniform(-2.0, 2.0, size=(200, 3))
        bounds = np.concatenate([rng.uniform(-1.5, 1.5, size=(3, 3)), rng.uniform(0.05, 0.9, size=(3, 1))], axis=1)
        inner = np.concatenate([bounds[:2, :3], 0.5 * bounds[:2, 3:]], axis=1)
        p[:5] = bounds[0, :3] + 0.5 * bounds[0, 3]  # inside a bounding sphere (and an inner one)
        visible = rng.random((len(p), len(d))) < 0.7
        every, run = visible.copy(), visible.copy()
        ip, ij = _meets(p, w, bounds, inner, every)
        jp, jj = _meets(p, w, bounds, inner, run, np.ascontiguousarray(rot[:, 1]))
        np.testing.assert_array_equal(ip, jp)
        np.testing.assert_array_equal(ij, jj)
        np.testing.assert_array_equal(every, run)
        assert 0 < len(ip) < visible.sum()


def test_embree_matches_the_numpy_caster(rng):
    p, n, d, bits, occ, rect, balls, rot = _random_case(rng)
    env = _env(rng)
    a = mesh_direct(p, n, env, rot, bits, occ, rect, balls, d)
    b = mesh_direct(p, n, env, rot, bits, occ, rect, balls, d, cast="numpy")
    np.testing.assert_allclose(a, b, atol=2 * 4 * np.pi / len(d) * 4.0)  # at most a grazing ray or two


def test_empty_input_gives_empty_output(rng):
    d = fibonacci_directions(64)
    e = mesh_direct(np.zeros((0, 3)), np.zeros((0, 3)), _env(rng), np.eye(3), np.zeros((0, 8), np.uint8), dirs=d)
    assert e.shape == (0, 3)
    assert self_blocked(np.zeros((0, 3)), np.zeros((0, 3)), *_ball([0, 0, 0]), d).shape == (0, 8)


# ------------------------------------------------------------------ the pipeline against brute force


def _scene():
    """A ground, an object of two boxes (it shadows itself; fitted with 2 spheres) and a ball (1 sphere)."""
    a = builtin_mesh(name="box", size=[0.5, 0.8, 0.5])
    b = builtin_mesh(name="box", size=[0.4, 0.4, 0.4])
    verts = np.concatenate([np.asarray(a.vertices) + [-0.35, 0.0, 0.0], np.asarray(b.vertices) + [0.35, -0.2, 0.0]])
    faces = np.concatenate([np.asarray(a.faces), np.asarray(b.faces) + len(a.vertices)])
    sc = Scene.from_dict({"objects": [
        {"name": "plane", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [4, 4]},
         "material": {"type": "diffuse", "albedo": [0.7] * 3}},
        {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.3, "subdivisions": 1},
         "transform": {"translate": [0.2, 0.3, 0.7]}, "material": {"type": "diffuse", "albedo": [0.8] * 3},
         "dynamic": True},
        {"name": "pair", "mesh": {"builtin": "box", "size": [1, 1, 1]},
         "transform": {"translate": [0.0, 0.45, 0.0], "rotate_deg": [0.0, 25.0, 0.0], "scale": 1.1},
         "material": {"type": "diffuse", "albedo": [0.6] * 3}, "dynamic": True}],
        "lights": [{"type": "environment", "constant": [1, 1, 1]}]})
    import trimesh

    sc.object("pair").mesh = trimesh.Trimesh(verts, faces, process=False)
    return sc


@pytest.fixture(scope="module")
def pair_scene():
    sc = _scene()
    pre = SphereLights.precompute(sc, {"n_spheres": {"pair": 2, "ball": 1, "plane": 1}, "fit_resolution": 12,
                                       "mesh_blockers": True}, cache=False, progress=False)
    return sc, pre


def _brute_force(sc, name, state, env, dirs):
    """The direct irradiance at an object's receivers: every rule direction above the tangent plane cast against
    every object's world mesh (the float64 caster) and the ground's rectangle."""
    from prtlab.spherelights._ground import ground_objects

    obj = sc.object(name)
    tr = state.transforms.get(name) or obj.transform
    p, n = obj.world_shading_points(tr), obj.world_normals(tr)
    w = dirs @ np.asarray(tr.rotation).T
    meshes = [(o.world_vertices(state.transforms.get(o.name) or o.transform), np.asarray(o.mesh.faces))
              for o in sc.objects if o.name in ("pair", "ball")]
    (_, rect), = ground_objects([sc.object("plane")], state.transforms)
    y0, cx, cz, ux, uz, vx, vz = rect
    caster = RayCaster(meshes)
    radiance = sh.basis(w, 10) @ env * (4 * np.pi / len(dirs))
    out = sh.basis(n, 10) @ sh.irradiance(env)
    for q in range(len(p)):
        c = w @ n[q]
        front = np.nonzero(c > 0)[0]
        hit = caster.occluded(np.broadcast_to(p[q], (len(front), 3)), w[front],
                              normals=np.broadcast_to(n[q], (len(front), 3)), method="numpy")
        t = (y0 - p[q, 1]) / w[front, 1]
        x, z = p[q, 0] + t * w[front, 0] - cx, p[q, 2] + t * w[front, 2] - cz
        ground = ((t > 0) & (np.abs((x * ux + z * uz) / (ux * ux + uz * uz)) <= 1)
                  & (np.abs((x * vx + z * vz) / (vx * vx + vz * vz)) <= 1))
        out[q] -= (c[front] * (hit | ground)) @ radiance[front]
    return out


@pytest.mark.parametrize("name", ["pair", "ball"])
def test_pipeline_equals_brute_force_ray_casting(pair_scene, name):
    sc, pre = pair_scene
    state = FrameState.from_scene(sc)
    res = pre.shade(state)
    env = pre._environment(state)
    expected = _brute_force(sc, name, state, env, fibonacci_directions(SphereLights._MESH_DIRECTIONS))
    albedo = np.asarray(sc.object(name).material.diffuse_albedo) / np.pi
    got = res.direct[name] / albedo
    # the own mesh's rays are cast in object space, the brute force's in world space: a grazing ray may differ
    one_ray = 4 * np.pi / SphereLights._MESH_DIRECTIONS
    assert np.abs(got - np.maximum(expected, 0)).max() <= 3 * one_ray
    assert np.mean(np.abs(got - np.maximum(expected, 0))) <= 0.05 * one_ray
    if name == "pair":  # the object does shadow itself
        open_sky = np.pi
        assert got.min() < 0.6 * open_sky


def test_rigid_motion_given_as_a_deformation_is_the_moved_object(pair_scene):
    """A rigid motion given as a deformation casts the own rays in the frame of the best-fit rotation: the moved
    object's rays, so the same direct light at every object."""
    from prtlab.scene import Transform, matrix_to_euler
    from tests.conftest import random_rotation

    sc, pre = pair_scene
    rot = random_rotation(np.random.default_rng(5))
    shift = np.array([0.1, 0.05, -0.2])
    obj = sc.object("pair")
    verts = np.asarray(obj.mesh.vertices, dtype=np.float64) @ rot.T + shift
    deformed = pre.shade(dataclasses.replace(FrameState.from_scene(sc), deformations={"pair": verts}))
    state = FrameState.from_scene(sc)
    tr = obj.transform
    state.transforms["pair"] = Transform(translate=tr.translate + tr.scale * tr.rotation @ shift,
                                         rotate_deg=matrix_to_euler(tr.rotation @ rot), scale=tr.scale)
    moved = pre.shade(state)
    assert not np.allclose(moved.direct["pair"], pre.shade(FrameState.from_scene(sc)).direct["pair"], atol=1e-3)
    for name in ("pair", "ball"):
        np.testing.assert_allclose(deformed.direct[name], moved.direct[name], atol=1e-10)


def test_the_objects_indirect_light_does_not_change(pair_scene):
    sc, pre = pair_scene
    state = FrameState.from_scene(sc)
    other = copy.copy(pre)
    other.__dict__ = dict(pre.__dict__)
    other.options = dataclasses.replace(pre.options, mesh_blockers=False)
    a, b = pre.shade(state), other.shade(state)
    for name in ("pair", "ball"):
        np.testing.assert_array_equal(a.indirect[name], b.indirect[name])
        assert not np.array_equal(a.direct[name], b.direct[name])


# ------------------------------------------------------------------ errors


def test_errors():
    d = fibonacci_directions(64)
    p = np.zeros((2, 3))
    with pytest.raises(TypeError, match="option mesh_blockers"):
        SphereLights.precompute(_scene(), {"mesh_blockers": 1, "n_spheres": 1}, cache=False, progress=False)
    with pytest.raises(ValueError, match=r"blocked_self must be \(P, ceil\(M / 8\)\)"):
        mesh_direct(p, p + [0, 1, 0], WHITE, np.eye(3), np.zeros((2, 3), np.uint8), dirs=d)
    with pytest.raises(ValueError, match="points and normals must have the same shape"):
        mesh_direct(p, np.zeros((3, 3)), WHITE, np.eye(3), _no_bits(p, 64), dirs=d)
    with pytest.raises(ValueError, match="points and normals must have the same shape"):
        self_blocked(p, np.zeros((3, 3)), *_ball([0, 0, 0]), d)
    with pytest.raises(ValueError, match="method"):
        mesh_direct(p, p + [0, 1, 0], WHITE, np.eye(3), _no_bits(p, 64), dirs=d, method="fast")
    with pytest.raises(ValueError, match="cast"):
        mesh_direct(p, p + [0, 1, 0], WHITE, np.eye(3), _no_bits(p, 64), dirs=d, cast="optix")
    with pytest.raises(ValueError, match="env_sh must have n\\*n rows"):
        mesh_direct(p, p + [0, 1, 0], np.ones((5, 3)), np.eye(3), _no_bits(p, 64), dirs=d)
    with pytest.raises(ValueError, match="scale must be a finite number > 0"):
        mesh_occluder(*_ball([0, 0, 0]), scale=0.0)
    assert isinstance(mesh_occluder(*_ball([0, 0, 0])), MeshOccluder)
