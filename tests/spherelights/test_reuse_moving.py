"""Tests of the ground's ray hits kept per object when some objects move (``_groundrays.ground_hits_update``,
``SphereLights.frame_reuse``): every frame equal to a fresh cast's or a fresh pipeline's, bit for bit, and rays in
fact kept."""

import dataclasses

import numpy as np
import pytest

from prtlab.geometry import builtin_mesh
from prtlab.pipeline import FrameState
from prtlab.spherelights._groundrays import (ground_direct_hits, ground_direct_sums, ground_hits_update,
                                             ground_light_hits, ground_light_sums, ground_ray_rule, mesh_blockers)
from prtlab.spherelights._meshdirect import (fibonacci_directions, mesh_direct_visible,
                                             mesh_direct_visible_update, mesh_occluder, self_blocked)
from tests.spherelights.test_reuse import _fresh, _moved, bunny_scene  # noqa: F401 (a fixture)

RULE = ground_ray_rule(32, 8)
# balls on a 6 x 6 ground: the four outer ones set the meshes' bounding box (so the rays' offset stays the same
# while the inner two move, turn, shrink or deform within it)
CENTRES = np.array([[-2.0, 0.5, 0.0], [2.0, 0.5, 0.0], [0.0, 0.5, -2.0], [0.0, 1.6, 2.0], [0.0, 0.6, 0.0],
                    [0.9, 0.6, 0.8]])
RADII = np.array([0.5, 0.5, 0.5, 0.5, 0.45, 0.4])


def _ball_meshes():
    m = builtin_mesh(name="icosphere", radius=1.0, subdivisions=2)
    v, f = np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces)
    return [(c + r * v, f) for c, r in zip(CENTRES, RADII)]


def _blocker_args(meshes, spheres=np.zeros((0, 4))):
    """``mesh_blockers``' arguments: each mesh in a ball around its vertices (as a deformed object's)."""
    bounds = []
    for v, _ in meshes:
        centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        bounds.append(np.append(centre, 1.000001 * np.linalg.norm(v - centre, axis=1).max()))
    return meshes, np.array(bounds), spheres, np.array([0.0, 0.0, 0.0]), 0.0, 3.0


def _ground_points(n=24):
    g = np.linspace(-2.9, 2.9, n)
    return np.stack(np.broadcast_arrays(g[:, None], 0.0, g[None, :]), -1).reshape(-1, 3)


def _assert_same_hits(ours, fresh):
    assert ours.n_points == fresh.n_points and len(ours.chunks) == len(fresh.chunks)
    for name in ("rows", "weights"):
        a, b = getattr(ours, name), getattr(fresh, name)
        assert (a is None) == (b is None) and (a is None or np.array_equal(a, b)), name
    for x, y in zip(ours.chunks, fresh.chunks):
        assert (x.start, x.stop) == (y.start, y.stop)
        for name in ("ptr", "ray_k", "face", "u", "v", "sphere_blocked"):
            a, b = getattr(x, name), getattr(y, name)
            assert (a is None) == (b is None), name
            if a is not None:
                assert a.dtype == b.dtype and np.array_equal(a, b), name


def _turned(v, degrees):
    t = np.radians(degrees)
    rot = np.array([[np.cos(t), 0.0, np.sin(t)], [0.0, 1.0, 0.0], [-np.sin(t), 0.0, np.cos(t)]])
    centre = v.mean(axis=0)
    return (v - centre) @ rot.T + centre


def _changes(meshes, rng):
    """Named frames: ``(meshes, moved flags)`` in sequence, each against the frame before."""
    inner, other = 4, 5
    v, f = meshes[inner]
    noise = 0.01 * rng.normal(size=v.shape)

    def only(k, new_v, base):
        return [(new_v, m[1]) if g == k else m for g, m in enumerate(base)]

    moved = only(inner, v + [0.02, 0.0, -0.01], meshes)
    turned = only(inner, _turned(v, 7.0), meshes)
    scaled = only(inner, 0.97 * (v - CENTRES[inner]) + CENTRES[inner], meshes)
    deformed = only(inner, v + noise, meshes)
    two = only(other, meshes[other][0] + [0.0, 0.03, 0.02], only(inner, v + [-0.03, 0.0, 0.02], meshes))
    return [("moved", moved), ("back", meshes), ("turned", turned), ("scaled", scaled), ("deformed", deformed),
            ("two moved", two), ("back again", meshes)]


@pytest.mark.parametrize("kind", ["closest", "blocked"])
@pytest.mark.parametrize("spacing", [0.0, 0.5])
@pytest.mark.parametrize("opaque", [False, True])
def test_kept_hits_equal_a_fresh_cast(rng, kind, spacing, opaque):
    """After moving, turning, scaling or deforming one ball of several, moving two and moving back, the hits of
    ``ground_hits_update`` from the frame before equal a fresh cast's bit for bit (the hit lists, faces,
    barycentrics, interpolation, opaque spheres' rays), rays were kept and some cast, and the sums agree."""
    cast = ground_light_hits if kind == "closest" else ground_direct_hits
    points = _ground_points()
    spheres = np.array([[1.5, 2.5, -1.0, 0.3]]) if opaque else np.zeros((0, 4))
    meshes = _ball_meshes()
    blockers = mesh_blockers(*_blocker_args(meshes, spheres))
    kept = cast(points, blockers, RULE, spacing=spacing)
    env = rng.normal(size=(16, 3))
    env[0] += 3.0
    previous = meshes
    for label, frame in _changes(meshes, rng):
        before = blockers
        blockers = mesh_blockers(*_blocker_args(frame, spheres))
        assert blockers.caster.epsilon == before.caster.epsilon, label  # the same rays' offset
        moved = [not np.array_equal(v, w) for (v, _), (w, _) in zip(frame, previous)]
        ours, counts = ground_hits_update(kept, points, blockers, moved, RULE, spacing=spacing)
        fresh = cast(points, blockers, RULE, spacing=spacing)
        _assert_same_hits(ours, fresh)
        if any(moved):
            assert counts["hits_kept"] > 0 and counts["rays_cast"] > 0, (label, counts)
        if kind == "closest":
            radiance = [rng.uniform(0, 1, (len(v), 3)) for v, _ in frame]
            for a, b in zip(ground_light_sums(ours, env, blockers, radiance),
                            ground_light_sums(fresh, env, blockers, radiance)):
                np.testing.assert_array_equal(a, b)
        else:
            np.testing.assert_array_equal(ground_direct_sums(ours, env, blockers),
                                          ground_direct_sums(fresh, env, blockers))
        kept, previous = ours, frame


def test_kept_hits_not_used_when_they_cannot_serve():
    """``ground_hits_update`` gives None (cast afresh) when the rays' offset changed (an outer ball moved out, the
    meshes' bounding box with it), another rule, or another number of faces; ``moved`` of the wrong length fails."""
    points = _ground_points(12)
    meshes = _ball_meshes()
    blockers = mesh_blockers(*_blocker_args(meshes))
    kept = ground_light_hits(points, blockers, RULE, spacing=0.5)
    out = [(v + [0.1, 0.0, 0.0], f) if g == 1 else (v, f) for g, (v, f) in enumerate(meshes)]
    moved = [g == 1 for g in range(len(meshes))]
    assert ground_hits_update(kept, points, mesh_blockers(*_blocker_args(out)), moved, RULE, spacing=0.5) is None
    assert ground_hits_update(kept, points, blockers, [False] * len(meshes), ground_ray_rule(16, 8),
                              spacing=0.5) is None
    fewer = [(v, f[:-1]) if g == 4 else (v, f) for g, (v, f) in enumerate(meshes)]
    assert ground_hits_update(kept, points, mesh_blockers(*_blocker_args(fewer)), [False] * len(meshes), RULE,
                              spacing=0.5) is None
    with pytest.raises(ValueError, match="moved must give one flag per mesh"):
        ground_hits_update(kept, points, blockers, [False], RULE, spacing=0.5)
    same, counts = ground_hits_update(kept, points, blockers, [False] * len(meshes), RULE, spacing=0.5)
    _assert_same_hits(same, kept)
    assert counts["rays_cast"] == 0 and counts["points_cast"] == 0


def test_kept_visible_rays_equal_a_fresh_computation(rng):
    """An unmoved receiver object's visible rays (``mesh_direct_visible_update``) after one occluder of several
    moves, turns, is deformed (a new occluder), two move, and all come back: equal to ``mesh_direct_visible``'s
    bit for bit, some rays recomputed and most kept; the ground and an opaque sphere blocking too."""
    meshes = _ball_meshes()
    dirs = fibonacci_directions(256)
    v, f = meshes[0]
    normals = (v - CENTRES[0]) / RADII[0]
    points = v + 1e-3 * normals
    bits = self_blocked(points, normals, v, f, dirs)
    rect = np.array([[0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 3.0]])
    balls = np.array([[-1.0, 2.2, 1.0, 0.3]])

    def occluder(g, shift=(0.0, 0.0, 0.0), turn=0.0, noise=None):
        w, faces = meshes[g]
        local = w - CENTRES[g]
        inner = np.append(np.zeros(3), 0.8 * RADII[g])[None]
        if noise is not None:  # a deformed object: its own caster, one ball around its vertices
            return mesh_occluder(w + noise, faces)
        t = np.radians(turn)
        rot = np.array([[np.cos(t), 0.0, np.sin(t)], [0.0, 1.0, 0.0], [-np.sin(t), 0.0, np.cos(t)]])
        centre = CENTRES[g] + shift
        return mesh_occluder(local, faces, rotation=rot, translate=centre, bounds=np.append(centre, RADII[g])[None],
                             inner=inner)

    rest = [occluder(g) for g in range(1, len(meshes))]
    frames = [("moved", {3: occluder(4, shift=(0.05, 0.0, 0.02))}), ("turned", {3: occluder(4, turn=20.0)}),
              ("deformed", {3: occluder(4, noise=0.01 * rng.normal(size=meshes[4][0].shape))}),
              ("two moved", {3: occluder(4, shift=(-0.05, 0.0, 0.0)), 4: occluder(5, shift=(0.0, 0.1, 0.0))}),
              ("back", {})]
    kept_occ = rest
    kept = mesh_direct_visible(points, normals, np.eye(3), bits, rest, rect, balls, dirs)
    for label, change in frames:
        occ = [change.get(i, o) for i, o in enumerate(rest)]
        moved = [a is not b for a, b in zip(occ, kept_occ)]
        ours, counts = mesh_direct_visible_update(kept, kept_occ, points, normals, np.eye(3), bits, occ, moved, rect,
                                                  balls, dirs)
        np.testing.assert_array_equal(ours, mesh_direct_visible(points, normals, np.eye(3), bits, occ, rect, balls,
                                                                dirs), err_msg=label)
        assert 0 < counts["rays_recomputed"] < counts["rays"] // 4, (label, counts)
        kept, kept_occ = ours, occ
    with pytest.raises(ValueError, match="moved must give one flag per occluder"):
        mesh_direct_visible_update(kept, kept_occ, points, normals, np.eye(3), bits, kept_occ, [True], rect, balls,
                                   dirs)


# ------------------------------------------------------------------ the pipeline: one object of several moving


def _same(a, b):
    for part in ("direct", "indirect", "total"):
        assert sorted(getattr(a, part)) == sorted(getattr(b, part))
        for name in getattr(b, part):
            assert np.array_equal(getattr(a, part)[name], getattr(b, part)[name]), f"{part} {name}"


def test_frames_with_some_objects_moving_are_a_fresh_pipelines(bunny_scene, monkeypatch):
    """Frames through one pipeline, one object or two moving (translated, turned, scaled, deformed), all three, the
    ground moving and everything coming back: each equals a fresh pipeline's frame bit for bit (every direct, indirect and
    total array), and where the objects' own sizes (so the rays' offset, ``_groundrays.object_size``) stay the same,
    a move or a turn included, the grounds' rays are partly kept (``info["geometry"]["updated"]``, rays kept and
    cast); ``ground_light``'s samples and the near caps of the objects that stay are partly kept, their ground's hidden
    projections at the surface samples kept whole. A kept frame's
    visible rays and ground rays are updated on the second thread (``run_ahead``), a fresh pipeline's made in turn."""
    import prtlab.spherelights._pipeline as pipeline
    from prtlab._tasks import concurrent_kernels, run_ahead

    ahead = []
    monkeypatch.setattr(pipeline, "run_ahead", lambda job: ahead.append(job.func.__name__) or run_ahead(job))
    scene, pre = bunny_scene
    pre.frame_reuse.clear()
    rest = FrameState.from_scene(scene)
    green, orange = rest.transforms["sphere_green"], rest.transforms["sphere_orange"]
    bunny = np.asarray(scene.object("bunny").mesh.vertices)
    up = dataclasses.replace(rest, transforms={**rest.transforms, "sphere_green": dataclasses.replace(
        green, translate=np.asarray(green.translate) + [0.0, 2e-3, 0.0])})
    two = _moved(up, "sphere_orange", translate=np.asarray(orange.translate) + [0.0, 1e-3, 0.0])
    every = _moved(_moved(_moved(two, "sphere_green", translate=np.asarray(green.translate) + [0.0, 3e-3, 0.0]),
                          "sphere_orange", translate=np.asarray(orange.translate) + [0.0, 2e-3, 0.0]),
                   "bunny", translate=np.asarray(rest.transforms["bunny"].translate) + [0.0, 0.0, 1e-3])
    # (label, state, the grounds' rays partly kept (None: the rays' offset may change), the objects' visible rays)
    frames = [
        ("rest", rest, False, False),
        ("one moved", up, True, True),
        ("two moved", two, True, True),
        # every object moved from the frame before (the sizes as before): more than MOVED_FRACTION of the meshes,
        # so the grounds' rays are all cast again; then the bunny back alone: updated again
        ("every object moved", every, False, False),
        ("bunny back", _moved(every, "bunny", translate=np.asarray(rest.transforms["bunny"].translate)), True, True),
        ("turned", _moved(rest, "sphere_green", rotate_deg=np.asarray(green.rotate_deg) + [0.0, 0.5, 0.0]), True,
         True),
        # 5 cm sideways: the meshes' bounding box changes, the rays' offset (the objects' own sizes) does not
        ("moved far", _moved(rest, "sphere_green", translate=np.asarray(green.translate) + [0.05, 0.0, -0.03]), True,
         True),
        ("moved far again", _moved(rest, "sphere_green", translate=np.asarray(green.translate) + [0.08, 0.0, -0.05]),
         True, True),
        ("scaled", _moved(rest, "sphere_green", scale=green.scale * 0.99), None, True),
        ("deformed", dataclasses.replace(rest, deformations={"bunny": bunny * [1.0, 0.99, 1.0]}), None, True),
        ("deformed again", dataclasses.replace(rest, deformations={"bunny": bunny * [1.0, 0.985, 1.0]}), None, True),
        ("ground moved", _moved(rest, "plane", translate=np.asarray(rest.transforms["plane"].translate)
                                + [0.05, 0.0, 0.0]), False, False),
        ("back", rest, False, False),
    ]
    kept_any = 0
    partly = [0, 0]  # updates of ground_light's samples or the near caps that kept some receivers; of ground_light
    for label, state, rays, visible in frames:
        ours = pre.shade(state)
        _same(ours, _fresh(pre).shade(state))
        updated = {}
        for name, counts in ours.info["geometry"]["updated"]:
            updated.setdefault(name[0], []).append(counts)
        if rays is not None:
            assert ({"ground_rays", "texel_rays"} <= set(updated)) == rays, (label, updated)
        assert ("mesh_direct" in updated) == visible, (label, updated)
        for counts in updated.get("ground_rays", []) + updated.get("texel_rays", []):
            assert counts["hits_kept"] > 0 and counts["rays_cast"] > 0, (label, counts)
            kept_any += 1
        for counts in updated.get("mesh_direct", []):
            assert 0 < counts["rays_recomputed"] < counts["rays"], (label, counts)
        if label in ("one moved", "moved far", "moved far again", "scaled"):  # green alone changed: the others kept
            made = [n for n in ours.info["geometry"]["computed"] if n[0] == "ground_projection"]
            kept = [n for n in ours.info["geometry"]["reused"] if n[0] == "ground_projection"]
            assert len(made) == 1 and len(kept) == 2, (label, made, kept)
        for counts in updated.get("ground_light", []) + updated.get("near_samples", []):
            assert counts["receivers_recomputed"] <= counts["receivers"], (label, counts)
            partly[0] += 0 < counts["receivers_recomputed"] < counts["receivers"]
        partly[1] += len(updated.get("ground_light", []))
    assert kept_any >= 4
    assert partly[0] >= 4 and partly[1] >= 4, partly  # ground_light's samples and the near caps partly kept
    # the kept frames' visible rays and ground rays on the side worker
    assert ahead.count("ground_hits") >= len(frames) - 1 and ahead.count("_mesh_direct") >= 2 * (len(frames) - 1)
    assert concurrent_kernels()


# ------------------------------------------------------------------ ground_light's samples when lights move


def _samples_equal(ours, fresh):
    assert ours.quad is fresh.quad and ours.n_grounds == fresh.n_grounds
    for name in ("ptr", "reals", "ints"):
        a, b = getattr(ours, name), getattr(fresh, name)
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a.view(np.uint8), b.view(np.uint8)), name


def _receivers_on_balls(centres, radii, n=300, seed=5):
    """Points just off the balls' surfaces with outward normals (unnormalised: the update must normalise as a fresh
    call), the ball each lies on."""
    rng = np.random.default_rng(seed)
    k = rng.integers(0, len(radii), n)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return centres[k] + 1.01 * radii[k, None] * d, 1.7 * d, k


def _moved_lights(centres, radii, label):
    """Copies of the lights' ``centres, radii`` as the scenario ``label`` changes them: ``"one moved"`` (light 4),
    ``"two moved"`` (lights 4 and 1), ``"grown"`` (light 5's radius); any other label leaves them as they are."""
    c, r = centres.copy(), radii.copy()
    if label == "one moved":
        c[4] += [0.15, -0.05, 0.1]
    elif label == "two moved":
        c[4] += [-0.1, 0.0, 0.05]
        c[1] += [0.0, 0.2, -0.3]
    elif label == "grown":
        r[5] *= 1.3
    return c, r


def _per_receiver(samples):
    return [(samples.reals[a:b].tobytes(), samples.ints[a:b].tobytes())
            for a, b in zip(samples.ptr[:-1], samples.ptr[1:])]


@pytest.mark.parametrize("grounds", [1, 2])
@pytest.mark.parametrize("with_local", [False, True])
def test_kept_ground_samples_equal_a_fresh_computation(grounds, with_local):
    """``ground_samples_update`` after one light moves, two move, one grows, one turns unadjusted, a local light
    moves, and all come back: equal to ``ground_samples`` bit for bit; receivers kept and recomputed; and in every
    changed frame some receiver's samples differ from the kept ones (the update cannot pass by keeping everything):
    each such receiver is among the recomputed."""
    from prtlab.spherelights._ground import ground_samples, ground_samples_update

    centres, radii = CENTRES.copy(), RADII.copy()
    points, normals, _ = _receivers_on_balls(centres, radii)
    rects = np.array([[0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 3.0], [-0.3, 1.0, 0.5, 1.5, 1.5, -1.0, 1.0]])[:grounds]
    local = np.full((len(radii), 3), np.nan)
    if with_local:
        local[3] = [2.0, 1.5, 1.0]
    unadjusted = np.arange(len(radii)) % 2 == 0

    def lights(label):
        c, r = _moved_lights(centres, radii, label)
        u, loc = unadjusted.copy(), local.copy()
        if label == "unadjusted":
            u[5] = not u[5]
        elif label == "local moved":
            c[3] += [0.4, -0.3, 0.0]
        return c, r, loc if with_local else None, u

    args = (points, normals, rects)
    kept_lights = lights("rest")
    kept = ground_samples(*args, *kept_lights[:3], unadjusted=kept_lights[3])
    for label in ["one moved", "back", "two moved", "grown", "unadjusted", "local moved", "back again", "rest"]:
        new = lights("rest" if label.startswith("back") else label)
        ours, counts = ground_samples_update(kept, kept_lights, *args, *new[:3], unadjusted=new[3])
        fresh = ground_samples(*args, *new[:3], unadjusted=new[3])
        _samples_equal(ours, fresh)
        differ = [q for q, (a, b) in enumerate(zip(_per_receiver(kept), _per_receiver(fresh))) if a != b]
        if label == "rest":  # nothing changed: all kept
            assert counts["lights_changed"] == 0 and counts["receivers_recomputed"] == 0, (label, counts)
        else:
            assert differ, label  # the change matters to some receivers
            assert 0 < counts["receivers_recomputed"] < counts["receivers"], (label, counts)
            assert len(differ) <= counts["receivers_recomputed"]
        kept, kept_lights = ours, new


def test_ground_samples_update_recomputes_every_receiver_a_light_reaches(monkeypatch):
    """A light moved next to a receiver above the ground changes its samples; with the reach test made to reach
    nothing the update keeps the old samples and differs from a fresh call (so the tests above would see a skipped
    receiver), and the update refuses kept samples of another number of lights or receivers."""
    from prtlab.spherelights import _ground

    rect = np.array([[0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 3.0]])
    points = np.array([[0.0, 1.0, 0.0], [2.0, 1.0, 2.0]])
    normals = np.array([[0.0, -1.0, 0.2], [0.0, 1.0, 0.0]])
    c0, r0 = np.array([[-2.5, 0.4, -2.5]]), np.array([0.3])
    c1 = np.array([[0.0, 0.5, 0.0]])  # under the first receiver: hides its ground
    kept = _ground.ground_samples(points, normals, rect, c0, r0)
    fresh = _ground.ground_samples(points, normals, rect, c1, r0)
    ours, counts = _ground.ground_samples_update(kept, (c0, r0, None, None), points, normals, rect, c1, r0)
    _samples_equal(ours, fresh)
    assert counts["receivers_recomputed"] >= 1
    assert _per_receiver(kept)[0] != _per_receiver(fresh)[0]

    def nothing(points, normals, quad, rects, spheres, flags, margin, out):
        out[:] = False

    monkeypatch.setattr(_ground, "_reached", nothing)
    skipped, _ = _ground.ground_samples_update(kept, (c0, r0, None, None), points, normals, rect, c1, r0)
    assert not np.array_equal(skipped.reals, fresh.reals) or not np.array_equal(skipped.ptr, fresh.ptr)
    monkeypatch.undo()
    assert _ground.ground_samples_update(kept, (np.zeros((2, 3)), np.ones(2), None, None), points, normals, rect,
                                         c1, r0) is None
    assert _ground.ground_samples_update(kept, (c0, r0, None, None), points[:1], normals[:1], rect, c1, r0) is None


# ------------------------------------------------------------------ the near blockers' caps when lights move


def _near_equal(ours, fresh):
    assert ours.order == fresh.order
    for name in ("normals", "visibility", "axis", "cos_half"):
        a, b = getattr(ours, name), getattr(fresh, name)
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a.view(np.uint8), b.view(np.uint8)), name


@pytest.mark.parametrize("n_near", [0, 2])
def test_kept_near_caps_equal_a_fresh_computation(n_near):
    """``near_blocker_visibility_update`` after one light moves, two move, one grows, one turns ineligible, and all
    come back, with receivers joining and leaving the kept rows: equal to ``near_blocker_visibility`` bit for bit,
    rows kept and recomputed, and in each changed frame some row differs from the kept one."""
    from prtlab.spherelights._nearcaps import near_blocker_visibility, near_blocker_visibility_update

    centres, radii = CENTRES.copy(), RADII.copy()
    points, normals, _ = _receivers_on_balls(centres, radii, n=400, seed=11)
    eligible = np.ones(len(radii), dtype=bool)
    eligible[2] = False

    def lights(label):
        c, r = _moved_lights(centres, radii, label)
        e = eligible.copy()
        if label == "ineligible":
            e[5] = False
        return c, r, e

    rng = np.random.default_rng(3)
    kept_lights, kept_sel = lights("rest"), rng.uniform(size=len(points)) < 0.8
    kept = near_blocker_visibility(points[kept_sel], normals[kept_sel], *kept_lights[:2], 4, n_near,
                                   eligible=kept_lights[2])
    for label in ["one moved", "back", "two moved", "grown", "ineligible", "back again", "rest"]:
        new = lights("rest" if label.startswith("back") else label)
        sel = rng.uniform(size=len(points)) < 0.8  # receivers in and out of the selection
        if label == "rest":
            sel = kept_sel
        rows = np.full(len(points), -1, dtype=np.int64)
        rows[kept_sel] = np.arange(kept_sel.sum())
        ours, counts = near_blocker_visibility_update(kept, kept_lights, points[sel], normals[sel], *new[:2], 4,
                                                      n_near, eligible=new[2], kept_from=rows[sel])
        fresh = near_blocker_visibility(points[sel], normals[sel], *new[:2], 4, n_near, eligible=new[2])
        _near_equal(ours, fresh)
        both = kept_sel[sel]  # rows of fresh whose receiver has a kept row
        differ = ~np.all(fresh.visibility[both] == kept.visibility[rows[sel][both]], axis=1)
        if label == "rest":
            assert counts["receivers_recomputed"] == 0, counts
        else:
            # (eligibility alone, ineligible and back, changes nothing without caps)
            assert differ.any() or label in ("ineligible", "back again") and n_near == 0, label
            assert (rows[sel] < 0).sum() < counts["receivers_recomputed"] < counts["receivers"], (label, counts)
        kept, kept_lights, kept_sel = ours, new, sel


def test_near_caps_update_recomputes_a_receiver_a_light_rises_above(monkeypatch):
    """A light moved from below a receiver's tangent plane to above it changes its row; with the reach test made to
    reach nothing the update keeps the old row and differs from a fresh call."""
    from prtlab.spherelights import _nearcaps

    points = np.array([[0.0, 1.0, 0.0], [3.0, 1.0, 0.0]])
    normals = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    c0, c1, r = np.array([[0.0, -1.0, 0.0]]), np.array([[0.0, 2.0, 0.0]]), np.array([0.5])
    kept = _nearcaps.near_blocker_visibility(points, normals, c0, r, 4, 2)
    fresh = _nearcaps.near_blocker_visibility(points, normals, c1, r, 4, 2)
    ours, counts = _nearcaps.near_blocker_visibility_update(kept, (c0, r, None), points, normals, c1, r, 4, 2)
    _near_equal(ours, fresh)
    assert counts["receivers_recomputed"] == 1 and not np.array_equal(kept.cos_half[0], fresh.cos_half[0])
    monkeypatch.setattr(_nearcaps, "_reached", lambda points, normals, spheres, margin: np.zeros(len(points), bool))
    skipped, _ = _nearcaps.near_blocker_visibility_update(kept, (c0, r, None), points, normals, c1, r, 4, 2)
    assert not np.array_equal(skipped.cos_half, fresh.cos_half)


def test_unique_keys_is_numpys(rng):
    """``_groundrays._unique_keys`` (the grid nodes of ``ground_ray_nodes``) gives ``np.unique``'s nodes and inverse,
    dense (a table) or sparse (a sort), empty included."""
    from prtlab.spherelights._groundrays import _unique_keys

    for high, shape in [(50, (300, 4)), (10**9, (300, 4)), (5, (0, 4)), (3000, (2000, 4))]:
        keys = rng.integers(0, high, size=shape)
        nodes, inverse = _unique_keys(keys)
        want_nodes, want_inverse = np.unique(keys, return_inverse=True)
        assert nodes.dtype == want_nodes.dtype and np.array_equal(nodes, want_nodes)
        assert np.array_equal(inverse.reshape(-1), want_inverse.reshape(-1))
