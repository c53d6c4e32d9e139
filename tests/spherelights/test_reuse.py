"""Tests of prtlab.spherelights._reuse (the frame's geometry-only ray results kept from frame to frame) and of the
split of the ray passes into their geometry and their sums (``_groundrays``, ``_meshdirect``)."""

import copy
import dataclasses

import numpy as np
import pytest

import prtlab
import prtlab.data
from prtlab.geometry import builtin_mesh
from prtlab.pipeline import FrameState
from prtlab.scene import EnvironmentLight
from prtlab.spherelights import SphereLights
from prtlab.spherelights._ground import ground_light, ground_sample_sums, ground_samples
from prtlab.spherelights._groundrays import (ground_direct_hits, ground_direct_rays, ground_direct_sums,
                                             ground_light_hits, ground_light_rays, ground_light_sums, ground_ray_rule,
                                             mesh_blockers)
from prtlab.spherelights._meshdirect import (fibonacci_directions, mesh_direct, mesh_direct_sums, mesh_direct_visible,
                                             mesh_occluder)
from prtlab.spherelights._nearcaps import near_blocker_direct, near_blocker_sums, near_blocker_visibility
from prtlab.spherelights._reuse import FrameReuse


def _ball(centre, radius=0.5, subdivisions=3):
    m = builtin_mesh(name="icosphere", radius=radius, subdivisions=subdivisions)
    return np.asarray(m.vertices) + np.asarray(centre, dtype=np.float64), np.asarray(m.faces)


def _env(rng, order=4):
    env = 0.3 * rng.normal(size=(order * order, 3))
    env[0] += 3.0
    return env


# ------------------------------------------------------------------ FrameReuse: exact inputs only


def test_reuse_only_for_exactly_equal_inputs():
    """Equal arrays reuse; a changed value, dtype, shape, ``-0.0`` for ``0.0`` or nesting computes again; an input
    changed in place after the call does not change the kept inputs; the same NaN bits reuse."""
    reuse = FrameReuse()
    calls = []

    def get(inputs):
        return reuse.get("x", inputs, lambda: calls.append(1) or len(calls))

    x = np.array([0.0, 1.0, np.nan])
    assert get((x, 2.0, "a")) == 1
    assert get((x.copy(), 2.0, "a")) == 1  # equal: reused
    for other in [(np.array([0.0, np.nextafter(1.0, 2.0), np.nan]), 2.0, "a"), (x.astype(np.float32), 2.0, "a"),
                  (x[:2], 2.0, "a"), (np.array([-0.0, 1.0, np.nan]), 2.0, "a"), (x, float(np.nextafter(2.0, 3.0)), "a"),
                  (x, 2.0, "b"), [x, 2.0, "a"], (x, 2, "a")]:
        n = len(calls)
        assert get(other) == n + 1, other
        assert get((x, 2.0, "a")) == n + 2  # back to the first inputs: computed again (one result kept per name)
    kept = np.array([1.0, 2.0])
    n = len(calls)
    get((kept,))
    kept[0] = 5.0  # changed in place: the kept copy still says 1.0
    assert get((kept,)) == n + 2


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int16, np.uint8, np.complex128])
def test_large_arrays_compared_by_their_bytes(rng, dtype):
    """Arrays above the in-place comparison's size (``_COMPARE_IN_PLACE``) are equal exactly when their bytes are:
    one changed element, ``-0.0`` for ``0.0`` and a strided view of the same values are seen as they are for small
    arrays; the same NaN bits are equal."""
    from prtlab.spherelights._reuse import _COMPARE_IN_PLACE, same_inputs

    n = 2 * _COMPARE_IN_PLACE // np.dtype(dtype).itemsize
    x = (rng.normal(size=n) * 100).astype(dtype)
    if np.dtype(dtype).kind in "fc":
        x[3] = np.nan
    assert x.nbytes >= _COMPARE_IN_PLACE
    assert same_inputs((x,), (x.copy(),))
    y = x.copy()
    y[n - 1] += 1
    assert not same_inputs((x,), (y,))
    if np.dtype(dtype).kind == "f":
        z, w = x.copy(), x.copy()
        z[5], w[5] = 0.0, -0.0
        assert not same_inputs((z,), (w,))
    wide = np.repeat(x, 2)
    assert same_inputs((wide[::2],), (x,))  # a strided view: compared by its values' bytes


def test_end_frame_forgets_what_the_frame_did_not_ask_for():
    reuse = FrameReuse()
    reuse.start_frame()
    reuse.get("a", (1,), lambda: "A")
    reuse.get("b", (1,), lambda: "B")
    assert reuse.end_frame() == {"computed": ["a", "b"], "reused": [], "updated": []}
    reuse.start_frame()
    assert reuse.get("a", (1,), lambda: "A2") == "A"
    assert reuse.end_frame() == {"computed": [], "reused": ["a"], "updated": []}
    reuse.start_frame()
    assert reuse.get("b", (1,), lambda: "B2") == "B2"  # "b" was forgotten at the end of the frame before
    reuse.clear()
    assert reuse.get("b", (1,), lambda: "B3") == "B3"


# ------------------------------------------------------------------ the ray passes: geometry once, any lighting


@pytest.mark.parametrize("opaque", [False, True])
@pytest.mark.parametrize("spacing", [0.0, 0.5])
def test_ground_hits_evaluate_any_lighting_as_the_whole_pass(rng, opaque, spacing):
    """The hits of one cast, evaluated under two environments and radiances, are the whole passes' results under
    each, bit for bit (with an opaque sphere and with the light interpolated between cast nodes)."""
    v1, f1 = _ball([0.2, 0.5, -0.1], 0.5)
    v2, f2 = _ball([1.3, 0.3, 0.4], 0.3, 2)
    bounds = np.array([[0.2, 0.5, -0.1, 0.51], [1.3, 0.3, 0.4, 0.31]])
    spheres = np.array([[-1.0, 1.0, 0.3, 0.3]]) if opaque else ()
    blk = mesh_blockers([(v1, f1), (v2, f2)], bounds, spheres, origin=[0.1, 0.0, 0.2], azimuth=0.3, scale=2.0)
    g = np.linspace(-2.5, 2.5, 23)
    pts = np.stack(np.broadcast_arrays(g[:, None], 0.0, g[None, :]), -1).reshape(-1, 3)
    rule = ground_ray_rule(24, 6)
    light_hits = ground_light_hits(pts, blk, rule, spacing=spacing)
    direct_hits = ground_direct_hits(pts, blk, rule, spacing=spacing)
    for _ in range(2):
        env = _env(rng)
        rad = [rng.uniform(0, 1, (len(v1), 3)), rng.uniform(0, 1, (len(v2), 3))]
        whole = ground_light_rays(pts, env, blk, rad, rule, spacing=spacing)
        for a, b in zip(ground_light_sums(light_hits, env, blk, rad), whole):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(ground_direct_sums(direct_hits, env, blk),
                                      ground_direct_rays(pts, env, blk, rule, spacing=spacing))
        ref = ground_light_rays(pts, env, blk, rad, rule, tier="reference", spacing=spacing)
        for a, b in zip(whole, ref):
            np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-14)
        assert np.abs(whole[1]).max() > 0.01


def test_mesh_direct_visible_rays_evaluate_any_lighting(rng):
    """``mesh_direct_sums`` of one ``mesh_direct_visible`` is ``mesh_direct`` under every environment, bit for bit
    (numba tier), and the reference tier's split is its reference within rounding."""
    v, f = _ball([0.0, 0.0, 0.0], 0.5)
    occ = [mesh_occluder(*_ball([1.1, 0.2, 0.0], 0.4))]
    d = fibonacci_directions(256)
    dirs = rng.normal(size=(300, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    p, n = 0.51 * dirs, dirs
    bits = np.zeros((len(p), 32), np.uint8)
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    rot *= np.sign(np.linalg.det(rot))
    rect = np.array([[-0.6, 0.0, 0.0, 3.0, 0.0, 0.0, 3.0]])
    visible = mesh_direct_visible(p, n, rot, bits, occ, rect, dirs=d)
    ref_visible = mesh_direct_visible(p, n, rot, bits, occ, rect, dirs=d, method="reference")
    np.testing.assert_array_equal(visible, ref_visible)
    for _ in range(2):
        env = _env(rng)
        whole = mesh_direct(p, n, env, rot, bits, occ, rect, dirs=d)
        np.testing.assert_array_equal(mesh_direct_sums(visible, n, env, rot, d), whole)
        np.testing.assert_allclose(mesh_direct_sums(visible, n, env, rot, d, method="reference"), whole,
                                   rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="visible must be"):
        mesh_direct_sums(visible[:, :3], n, _env(rng), rot, d)


def test_ground_samples_evaluate_any_lighting_as_ground_light(rng):
    """``ground_sample_sums`` of one ``ground_samples`` is ``ground_light`` under other textures, environments and
    local radiances, bit for bit: two grounds, adjusted and exact lights, a local light beyond a ground, receivers
    below a ground and none at all."""
    pts = np.stack([rng.uniform(-2, 2, 300), rng.uniform(-0.2, 1.5, 300), rng.uniform(-2, 2, 300)], axis=1)
    nrm = rng.normal(size=(300, 3))
    rects = np.array([[0.0, 0.0, 0.0, 2.0, 0.3, -0.3, 2.0], [-0.5, 1.0, 0.5, 3.0, 0.0, 0.0, 3.0]])
    c = np.array([[0.3, 0.5, 0.2], [-1.0, 0.8, 0.5], [0.5, -1.5, 0.0], [1.5, 0.4, -1.0]])
    r = np.array([0.4, 0.3, 0.5, 0.2])
    loc = np.full((4, 3), np.nan)
    loc[2] = [5.0, 4.0, 3.0]
    exact = np.array([True, False, False, False])
    samples = ground_samples(pts, nrm, rects, c, r, loc, unadjusted=exact)
    assert (samples.ints[:, 1] < 0).any() and (np.diff(samples.ptr) == 0).any()  # a local light beyond, empty rows
    for _ in range(2):
        tex, env = rng.uniform(0, 1, (2, 8, 8, 3)), _env(rng)
        loc[2] = rng.uniform(1, 5, 3)
        whole = ground_light(pts, nrm, rects, tex, env, c, r, loc, unadjusted=exact)
        for a, b in zip(ground_sample_sums(samples, tex, env, loc), whole):
            np.testing.assert_array_equal(a, b)
    empty = ground_samples(np.zeros((0, 3)), np.zeros((0, 3)), rects, c, r)
    assert [x.shape for x in ground_sample_sums(empty, tex, env)] == [(0, 3), (0, 3)]
    with pytest.raises(ValueError, match="textures must have shape"):
        ground_sample_sums(samples, tex[:1], env, loc)


@pytest.mark.parametrize("method", ["numba", "reference"])
def test_near_blocker_visibility_evaluates_any_lighting(rng, method):
    """``near_blocker_sums`` of one ``near_blocker_visibility`` is ``near_blocker_direct`` under other
    environments, bit for bit (each tier), with caps taken and without (``n_near = 0``), some lights not
    eligible."""
    c = np.array([[0.0, 0.6, 0.0], [0.8, 0.3, 0.2], [-0.7, 0.4, -0.3], [0.2, 0.5, 0.9]])
    r = np.array([0.35, 0.3, 0.25, 0.2])
    p = np.stack([rng.uniform(-1.2, 1.2, 60), np.zeros(60), rng.uniform(-1.2, 1.2, 60)], axis=1)
    n = np.tile([0.1, 1.0, 0.0], (60, 1))  # not unit: normalised once, in the visibility
    elig = np.array([True, True, False, True])
    for k in (2, 0):
        vis = near_blocker_visibility(p, n, c, r, 4, k, eligible=elig, method=method)
        for _ in range(2):
            env = rng.normal(size=(100, 3))
            env[0] += 5.0
            np.testing.assert_array_equal(near_blocker_sums(vis, env, method=method),
                                          near_blocker_direct(p, n, c, r, env, 4, k, eligible=elig, method=method))


# ------------------------------------------------------------------ the pipeline: reuse only when nothing moved


@pytest.fixture(scope="module")
def bunny_scene():
    scene = prtlab.load_scene(prtlab.data.scene_path("bunny_spheres_env"))
    pre = SphereLights.precompute(scene, {"n_spheres": {"bunny": 4, "sphere_green": 1, "sphere_orange": 1},
                                          "fit_resolution": 12}, cache=False, progress=False)
    return scene, pre


def _fresh(pre):
    """A pipeline with the same precomputation and nothing kept from any frame."""
    other = copy.copy(pre)
    other.__dict__["_frame_reuse"] = FrameReuse()
    return other


def _same(a, b):
    for part in ("direct", "indirect", "total"):
        for name in getattr(b, part):
            np.testing.assert_array_equal(getattr(a, part)[name], getattr(b, part)[name], err_msg=f"{part} {name}")


def _moved(state, name, **change):
    tr = state.transforms.get(name)
    return dataclasses.replace(state, transforms={**state.transforms, name: dataclasses.replace(tr, **change)})


def _relit(state, shift):
    """The environment map turned about +Y by ``shift`` columns (a new light object)."""
    env = state.lights[0]
    return dataclasses.replace(state, lights=[dataclasses.replace(env, image=np.roll(env.image, shift, axis=1))])


def test_frames_after_any_change_are_a_fresh_pipelines(bunny_scene):
    """A sequence of frames through one pipeline: the environment alone changing reuses every geometry-only result
    (named in ``info["geometry"]``) and gives the fresh pipeline's result bit for bit; moving, turning or scaling
    one object, deforming one, moving the ground, and coming back to the first pose each give a fresh pipeline's
    result bit for bit (nothing stale reused)."""
    scene, pre = bunny_scene
    pre.frame_reuse.clear()
    rest = FrameState.from_scene(scene)
    assert isinstance(rest.lights[0], EnvironmentLight) and rest.lights[0].image is not None
    first = pre.shade(rest)
    kinds = {k if isinstance(k, str) else k[0] for k in first.info["geometry"]["computed"]}
    assert kinds == {"mesh_blockers", "texel_rays", "ground_rays", "mesh_direct", "ground_light", "near_samples",
                     "covered_texels", "ground_projection"}
    assert first.info["geometry"]["reused"] == []
    _same(first, _fresh(pre).shade(rest))

    relit = _relit(rest, 37)
    again = pre.shade(relit)
    assert again.info["geometry"]["computed"] == []
    assert sorted(map(str, again.info["geometry"]["reused"])) == sorted(map(str, first.info["geometry"]["computed"]))
    _same(again, _fresh(pre).shade(relit))
    assert not np.array_equal(again.total["plane"], first.total["plane"])

    tr = rest.transforms["sphere_green"]
    bunny = np.asarray(scene.object("bunny").mesh.vertices)
    changes = {
        "moved": _moved(relit, "sphere_green", translate=np.asarray(tr.translate) + [1e-3, 0.0, 0.0]),
        "turned": _moved(relit, "sphere_green", rotate_deg=np.asarray(tr.rotate_deg) + [0.0, 0.5, 0.0]),
        "scaled": _moved(relit, "sphere_green", scale=tr.scale * 1.01),
        "deformed": dataclasses.replace(relit, deformations={"bunny": bunny * [1.0, 1.02, 1.0]}),
        "ground moved": _moved(relit, "plane", translate=np.asarray(rest.transforms["plane"].translate)
                               + [0.05, 0.0, 0.0]),
        "back": relit,
    }
    for label, state in changes.items():
        ours = pre.shade(state)
        assert "mesh_blockers" in ours.info["geometry"]["computed"], label
        _same(ours, _fresh(pre).shade(state))
    # a deformation kept, the environment alone changing: the deformed object's own rays are reused too
    deformed = changes["deformed"]
    pre.shade(deformed)
    ours = pre.shade(_relit(deformed, 11))
    assert ours.info["geometry"]["computed"] == [] and ("self_blocked", "bunny") in ours.info["geometry"]["reused"]
    _same(ours, _fresh(pre).shade(_relit(deformed, 11)))


def test_a_translation_array_changed_in_place_is_seen(bunny_scene):
    """A frame state whose transform's translation array is changed in place between frames (the same objects)
    casts again: the kept inputs are copies."""
    scene, pre = bunny_scene
    pre.frame_reuse.clear()
    state = FrameState.from_scene(scene)
    tr = dataclasses.replace(state.transforms["sphere_orange"],
                             translate=np.array(state.transforms["sphere_orange"].translate, dtype=np.float64))
    state = dataclasses.replace(state, transforms={**state.transforms, "sphere_orange": tr})
    pre.shade(state)
    tr.translate[2] += 0.01
    ours = pre.shade(state)
    assert "mesh_blockers" in ours.info["geometry"]["computed"]
    _same(ours, _fresh(pre).shade(state))


def test_update_gives_a_kept_result_from_the_last():
    """With ``update``, changed inputs give ``update(kept inputs, kept result)``'s result (named in ``updated``
    with its counts) unless it returns None (then ``compute()``); equal inputs still reuse."""
    reuse = FrameReuse()
    reuse.start_frame()
    assert reuse.get("a", (1,), lambda: 10) == 10
    reuse.end_frame()
    reuse.start_frame()
    assert reuse.get("a", (2,), lambda: -1, lambda inputs, value: (value + inputs[0], {"kept": 1})) == 11
    assert reuse.end_frame() == {"computed": [], "reused": [], "updated": [("a", {"kept": 1})]}
    reuse.start_frame()
    assert reuse.get("a", (2,), lambda: -1, lambda inputs, value: None) == 11  # the same inputs: reused
    assert reuse.get("a", (3,), lambda: -1, lambda inputs, value: None) == -1  # no update: computed
    assert reuse.end_frame() == {"computed": ["a"], "reused": ["a"], "updated": []}


def test_kept_by_key_keeps_the_last_results_read_only():
    """``kept_by_key`` makes a missing entry once, returns it read-only, and drops the oldest past its size."""
    from prtlab.spherelights._reuse import kept_by_key

    cache, made = {}, []

    def make(k):
        made.append(k)
        return np.full(3, float(k))

    for k in (1, 2, 1, 3, 4):
        out = kept_by_key(cache, k, lambda: make(k), size=2)
        assert out[0] == k and not out.flags.writeable
    assert made == [1, 2, 3, 4] and list(cache) == [3, 4]
