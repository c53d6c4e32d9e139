"""Tests of prtlab/interreflection/_pipeline.py: one bounce between two objects against Monte Carlo,
moving objects, the api entry point.

Goals (Iwasaki et al. 2007 as issue 15 sets them): relative RMS of per-vertex radiance 5 % on the
total and 15 % on the indirect light, the direct light held to the total's 5 %, scored with
:func:`prtlab.compare` (the reference's noise in quadrature, :meth:`prtlab.metrics.ComparisonRow.meets`;
:meth:`prtlab.metrics.Comparison.check` refuses a reference noisier than a third of the goal).
Where only a per-object mean is affordable, :func:`mean_bound` holds it to the same goal: ``rel_rms <= g``
implies ``|mean(ours - ref)| <= g rms(ref)`` (``|mean d| <= rms d``), and ``MC_SIGMAS`` standard
errors of the reference's mean are added (a confidence interval, not a noise budget).

The quick ball over a red floor (order-4 SH, 8 radii x 6 x 8 x 8 spheres, degree 31, PCA with N = 8
from 64 lights) against 4,096 paths per vertex: the floor's indirect light (the ball's bounce light)
misses the indirect goal (``test_the_floors_bounce_light_is_within_the_goal``, a strict xfail; the
fidelity tier repeats the whole scene with 16,384 paths, ``tests/fidelity/test_interreflection.py``).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import prtlab
from prtlab.interreflection import PAPER_OPTIONS, Interreflection, InterreflectionOptions, shade_scene
from prtlab.pipeline import FrameState
from prtlab.reference import path_trace
from prtlab.scene import AreaLight, PointLight, Transform
from tests.conftest import MC_SIGMAS, two_numba_threads
from tests.scenes import ball_over_floor

QUICK = dict(n_radii=8, resolution=8, degree=31, n_lights=64, n_basis=8)
#: The paper's goals: relative RMS of per-vertex radiance (direct held to the total's goal).
GOAL = {"direct": 0.05, "indirect": 0.15, "total": 0.05}
#: Paths per vertex of the ball-over-floor reference: relative noise 0.006-0.009 (direct, total) and
#: 0.017 (ball indirect), within a third of the goals; the floor's indirect 0.085 is not (its xfail).
PATHS = 4096


def mean_bound(ours, truth, stderr, goal):
    """``(|mean(ours - truth)|, goal * rms(truth) + MC_SIGMAS * se)`` per channel over the vertices.

    ``rel_rms <= goal`` implies the first is at most ``goal * rms(truth)`` (``|mean d| <= rms d``);
    ``se``, the standard error of the reference's mean, adds ``MC_SIGMAS`` of its confidence interval.
    """
    ours, truth = np.asarray(ours), np.asarray(truth)
    err = np.abs(np.mean(ours - truth, axis=0))
    se_mean = np.sqrt(np.sum(np.asarray(stderr) ** 2, axis=0)) / len(truth)
    return err, goal * np.sqrt(np.mean(truth**2, axis=0)) + MC_SIGMAS * se_mean


def scene():
    s = ball_over_floor({"type": "diffuse", "albedo": [0.8, 0.3, 0.3]})
    s.objects[1].transform.translate[1] = 0.7
    return s


@pytest.fixture(scope="module")
def cache_root(tmp_path_factory):
    return tmp_path_factory.mktemp("prtlab-cache")


@pytest.fixture(scope="module")
def pre(cache_root):
    from prtlab.cache import Cache

    return Interreflection.precompute(scene(), QUICK, cache=Cache(cache_root, progress=False), progress=False)


@pytest.fixture(scope="module")
def reference(pre):
    """One bounce of the quick ball over floor by Monte Carlo, ``PATHS`` paths per vertex."""
    return path_trace(pre.scene, 1, PATHS, np.random.default_rng(11))


def test_one_bounce_between_two_objects_against_monte_carlo(pre, reference):
    """Direct and total light of both objects and the ball's indirect light within the goals, per vertex."""
    res = pre.shade(bounces=1)
    comparison = prtlab.compare(res, reference)
    failures = [*comparison.check(GOAL["total"], parts=("direct", "total")),
                *comparison.check(GOAL["indirect"], parts=("indirect",), objects=("ball",))]
    assert not failures, failures
    # the red floor tints the ball's indirect light red
    ind = res.indirect["ball"].mean(0)
    assert ind[0] > 1.5 * ind[1]


def test_the_floors_bounce_light_is_within_the_goal(pre, reference):
    """The floor's indirect light against ``PATHS`` paths: its reference noise (0.085) is above a third of
    the goal, which only widens the budget ``hypot(goal, noise)``; a miss is still a miss. (Without the
    residual gather, ``residual_rays=0``, it missed: 0.313, the ball's N = 8 PCA radiance too bright.)"""
    res = pre.shade(bounces=1)
    row = prtlab.compare(res, reference, objects=["floor"], parts=["indirect"]).row("floor", "indirect")
    print(f"\nfloor indirect: {row}")
    assert row.meets(GOAL["indirect"]), row
    err, bound = mean_bound(res.indirect["floor"], reference.indirect["floor"], reference.stderr["indirect"]["floor"],
                            GOAL["indirect"])
    assert np.all(err <= bound), (err, bound)


def _vertex_areas(mesh) -> np.ndarray:
    """A third of the area of each vertex's triangles (the vertices' share of the surface)."""
    areas = np.zeros(len(mesh.vertices))
    np.add.at(areas, np.asarray(mesh.faces).ravel(), np.repeat(mesh.area_faces / 3.0, 3))
    return areas


@pytest.mark.parametrize("variant", ["defaults", "occluder_basis"])
def test_more_bounces_add_light_and_converge(pre, cache_root, variant):
    """Each bounce adds light to every object, and its flux is at most the largest albedo times the flux of the
    bounce before (energy conservation for Lambertian surfaces: bounce ``k + 1`` reflects at most the light that
    bounce ``k`` leaves with; per channel, the area-weighted sum of the radiance each bounce adds). Per object the
    bounces need not shrink: the ball's third bounce sums to more over its vertices than its second (the floor's
    second-bounce light lies under the ball). Defaults; and the basis trained with the other objects' shadows,
    ``pca_occluders=True``, without the residual gather."""
    if variant != "defaults":
        from prtlab.cache import Cache

        pre = Interreflection.precompute(scene(), dict(QUICK, pca_occluders=True, residual_rays=0),
                                         cache=Cache(cache_root, progress=False), progress=False)
    zero, one, two, three = (pre.shade(bounces=b) for b in (0, 1, 2, 3))
    assert all(np.all(v == 0) for v in zero.indirect.values())
    objects = pre.scene.objects
    albedo_max = np.max([o.material.albedo for o in objects], axis=0)
    flux = []
    for before, after in ((zero, one), (one, two), (two, three)):
        added = {o.name: after.indirect[o.name] - before.indirect[o.name] for o in objects}
        assert all(added[name].sum() > 0 for name in added)
        flux.append(sum((_vertex_areas(o.mesh)[:, None] * added[o.name]).sum(0) for o in objects))
    for o in objects:
        np.testing.assert_array_equal(one.direct[o.name], three.direct[o.name])
    assert np.all(flux[1] <= albedo_max * flux[0]) and np.all(flux[2] <= albedo_max * flux[1]), (flux, albedo_max)


def test_moving_an_object_equals_a_from_scratch_shade(pre):
    moved = Transform(translate=np.array([0.4, 0.8, -0.2]), rotate_deg=np.array([0.0, 40.0, 0.0]))
    state = FrameState.from_scene(pre.scene)
    state.transforms["ball"] = moved
    first = pre.shade(state, bounces=2)
    assert first.info["computed_pairs"] == 2
    again = pre.shade(state, bounces=2)
    assert again.info["reused_pairs"] == 2 and again.info["computed_pairs"] == 0
    fresh = Interreflection(pre.scene, pre.options, pre.data).shade(state, bounces=2)
    for name in ("floor", "ball"):
        np.testing.assert_array_equal(first.total[name], fresh.total[name])
        np.testing.assert_array_equal(again.total[name], fresh.total[name])
    # the step that reuses every pair at once (nothing moved) against each pair's own key
    pre.reuse.irradiance_step = None
    per_pair = pre.shade(state, bounces=2)
    counts = ("computed_pairs", "updated_pairs", "updated_rows", "skipped_pairs", "reused_pairs")
    assert [per_pair.info[k] for k in counts] == [again.info[k] for k in counts]
    for name in ("floor", "ball"):
        np.testing.assert_array_equal(per_pair.total[name], again.total[name])
    # relighting only (same poses as the previous frame): every pair is reused
    state.lights = [type(pre.scene.lights[0])(image=pre.scene.lights[0].image * 2.0)]
    relit = pre.shade(state, bounces=2)
    assert relit.info["reused_pairs"] == 2
    np.testing.assert_allclose(relit.total["ball"], 2.0 * fresh.total["ball"], rtol=1e-10)


def test_shadow_blockers_after_a_move_equal_fresh_bounds(pre):
    """The shadow rays' blocker bounds kept per object (made again only for an object that moved) equal
    :func:`blocker_bounds` computed afresh at the new poses, for every shooting object."""
    from prtlab.interreflection._direct_rays import blocker_bounds

    pipeline = Interreflection(pre.scene, pre.options, pre.data)
    state = FrameState.from_scene(pre.scene)
    for translate in ([0.0, 0.7, 0.0], [0.3, 0.9, -0.1]):
        state.transforms["ball"] = Transform(translate=np.array(translate), rotate_deg=np.array([0.0, 30.0, 0.0]))
        geo = pipeline._frame_geometry(state)
        poses = tuple(geo[o.name]["pose"] for o in pipeline.objects)
        caster, _ = pipeline._scene_caster(geo, poses)
        flat = [pipeline.flat[o.name] for o in pipeline.objects]
        for me in range(len(pipeline.objects)):
            for vertices in (False, True):
                name = pipeline.objects[me].name
                exclude = me if flat[me] or (vertices and pipeline.convex[name]) else None
                for kept, fresh in zip(pipeline._shadow_blockers(caster, poses, me, vertices),
                                       blocker_bounds(caster, flat, exclude)):
                    np.testing.assert_array_equal(kept, fresh)


def test_moving_an_object_recomputes_only_the_pairs_it_touches(pre):
    """Three objects: a far third ball moves; pairs not involving it (and out of its field's reach) are
    reused, and the result equals a from-scratch shade."""
    from prtlab.scene import SceneObject

    base = pre.scene
    far = SceneObject("far", base.object("ball").mesh, Transform(translate=np.array([30.0, 0.7, 0.0])),
                      base.object("ball").material)
    sc = type(base)(objects=[*base.objects, far], lights=base.lights, camera=base.camera)
    data = {**pre.data, "far": pre.data["ball"]}
    ir = Interreflection(sc, pre.options, data)
    state = FrameState.from_scene(sc)
    ir.shade(state, bounces=1)
    state.transforms["far"] = Transform(translate=np.array([31.0, 0.7, 0.0]))
    moved = ir.shade(state, bounces=1)
    assert moved.info["reused_pairs"] == 2 and moved.info["computed_pairs"] == 4
    fresh = Interreflection(sc, pre.options, data).shade(state, bounces=1)
    for name in ("floor", "ball", "far"):
        np.testing.assert_allclose(moved.total[name], fresh.total[name], rtol=1e-12, atol=1e-15)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_factors=st.integers(0, 3))
def test_visibility_product_kernel_equals_the_product_tier(pre, seed, n_factors):
    """The in-place masked product (``_visibility``'s kernel) equals ``prtlab.sh.product`` applied to the
    masked rows, factor after factor, at any subset of rows (empty included)."""
    rng = np.random.default_rng(seed)
    n_v, n2 = 50, pre.options.order ** 2
    g = {"self": rng.normal(size=(n_v, n2))}
    occ = {f"o{i}": rng.normal(size=(n_v, n2)) for i in range(n_factors)}
    rows = np.sort(rng.choice(n_v, size=int(rng.integers(0, n_v)), replace=False))
    factors = [(name, rng.random(len(rows)) < 0.6) for name in occ]
    fast = pre._visibility(g, occ, factors, rows)
    ref = pre._visibility(g, occ, factors, rows, method="reference")
    np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-12)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_rows=st.sampled_from([0, 1, 63, 64, 65, 255, 256, 257, 700, 2100]))
def test_one_visibility_kernel_call_equals_one_call_per_factor(pre, seed, n_rows):
    """``_visibility``'s one kernel call for every factor (``visibility_product_kernel`` and its serial twin)
    gives the per-factor kernel calls' arrays bit for bit: factors in a random order, a field used twice, masks
    empty, full, sparse and overlapping, signed zeros, row counts about a tile, a block and (with 5 factors at
    2,100 rows) ``SERIAL_ITEMS`` products."""
    from prtlab.interreflection import _kernels
    from prtlab.interreflection._pipeline import OcclusionFields, _gaunt_runs

    rng = np.random.default_rng(seed)
    n_v, n2 = n_rows + 40, pre.options.order ** 2
    g = {"self": rng.normal(size=(n_v, n2))}
    names = ["a", "b", "c", "d"]
    occ = OcclusionFields(names, rng.normal(size=(len(names), n_v, n2)))
    g["self"][: n_v // 7] *= rng.choice([0.0, -0.0, 1.0], size=(n_v // 7, n2))  # signed zeros in the sums
    occ.fields[0, : n_v // 5, 1:] = -0.0
    rows = np.sort(rng.choice(n_v, size=n_rows, replace=False))
    density = [1.0, 0.0, 0.05, 0.5, 0.9]
    factors = [(name, rng.random(n_rows) < density[i])
               for i, name in enumerate([*rng.permutation(names), rng.choice(names)])]
    per_factor = pre._visibility(g, occ, factors, rows, method="per_factor")
    fused = pre._visibility(g, occ, factors, rows)
    assert fused.shape == (n_rows, n2)
    assert np.array_equal(fused, per_factor)
    masks = np.array([m for _, m in factors], bool).reshape(len(factors), n_rows)
    which = np.array([occ.index[name] for name, _ in factors], np.int64)
    for kernel in (_kernels.visibility_product_kernel, _kernels.visibility_product_serial):
        vis = np.ascontiguousarray(g["self"][rows])
        kernel(vis, occ.fields, which, masks, rows, *_gaunt_runs(4))
        assert np.array_equal(vis, per_factor)
    as_dict = pre._visibility(g, dict(occ), factors, rows)  # plain mapping: its fields stacked first
    assert np.array_equal(as_dict, per_factor)
    if n_rows >= 1000:
        assert np.count_nonzero(masks) >= _kernels.SERIAL_ITEMS


def test_moved_frame_is_the_same_with_one_visibility_kernel_call_per_factor(pre, monkeypatch):
    """A frame after a move, shaded with ``_visibility``'s one call for every factor and with one call per
    factor (fresh pipelines, the same poses), gives the same arrays bit for bit."""
    def shaded(method):
        monkeypatch.setattr(Interreflection, "_visibility", functools.partialmethod(visibility, method=method))
        ir = Interreflection(pre.scene, pre.options, pre.data)
        ir.shade(bounces=1)
        state = FrameState.from_scene(pre.scene)
        state.transforms["ball"] = Transform(translate=[0.1, 0.65, 0.05])
        return ir.shade(state, bounces=1)

    visibility = Interreflection._visibility
    fused, per_factor = shaded("numba"), shaded("per_factor")
    for name in fused.total:
        for part in ("direct", "indirect", "total"):
            assert np.array_equal(getattr(fused, part)[name], getattr(per_factor, part)[name])


class _Stalled:
    """A frame worker that runs the first task it is given (step 1) and leaves the others pending, so the frame's
    own thread makes every residual-gather entry."""

    def __init__(self):
        self.calls = 0

    def submit(self, fn, *args):
        from concurrent.futures import Future

        self.calls += 1
        future = Future()
        if self.calls == 1:
            future.set_result(fn(*args))
        return future


def _moving_frames(pre):
    """Frames of a fresh pipeline, two bounces: the first, the ball moved twice, an area light added and moved with
    the ball (twice), then the light alone moved."""
    from prtlab.scene import AreaLight

    ir = Interreflection(pre.scene, pre.options, pre.data)
    state = FrameState.from_scene(pre.scene)
    out = [ir.shade(state, bounces=2)]
    for translate in ([0.1, 0.65, 0.05], [-0.05, 0.6, 0.1]):
        state.transforms["ball"] = Transform(translate=translate)
        out.append(ir.shade(state, bounces=2))
    for centre, ball in (([0.2, 2.0, 0.1], True), ([0.0, 2.2, 0.1], True), ([0.1, 2.1, 0.0], False)):
        state.lights = [*pre.scene.lights, AreaLight(center=np.array(centre), u=np.array([0.3, 0, 0]),
                                                     v=np.array([0, 0, 0.3]), radiance=np.full(3, 5.0))]
        if ball:
            state.transforms["ball"] = Transform(translate=[0.05, 0.6 + centre[1] / 10, 0.0])
        out.append(ir.shade(state, bounces=2))
    return out


def _assert_same_frames(frames, others):
    """Every object's direct, indirect and total light equal bit for bit, and the ray and pair counts."""
    for a, b in zip(frames, others, strict=True):
        for key in ("residual_rays_cast", "direct_rays_cast", "residual_near_hits", "residual_near_rays_cast",
                    "computed_pairs", "updated_pairs"):
            assert a.info[key] == b.info[key], key
        for name in a.total:
            for part in ("direct", "indirect", "total"):
                assert np.array_equal(getattr(a, part)[name], getattr(b, part)[name])


@pytest.mark.parametrize("worker", ["thread", "stalled"])
def test_overlapped_frames_equal_sequential_frames(pre, monkeypatch, worker):
    """Frames with ``OVERLAP`` (step 1 and the residual-gather entries on a second thread, or every entry taken
    back by the frame's thread) equal frames without it bit for bit, ray counts included (``_moving_frames``)."""
    from prtlab import _tasks
    from prtlab.interreflection import _pipeline

    monkeypatch.setattr(_pipeline, "OVERLAP", False)
    sequential = _moving_frames(pre)
    monkeypatch.setattr(_pipeline, "OVERLAP", True)
    if worker == "stalled":
        monkeypatch.setattr(_tasks, "side_worker", lambda: _Stalled())
    _assert_same_frames(sequential, _moving_frames(pre))
    assert sequential[1].info["residual_rays_cast"] > 0


def test_task_frames_equal_serial_frames(pre, monkeypatch):
    """Frames with ``TASKS`` (each object's direct light, near-hit light and bounce as a task on one numba thread)
    equal frames without it bit for bit, ray counts included (``_moving_frames``)."""
    from prtlab import _tasks

    two_numba_threads()
    monkeypatch.setattr(_tasks, "TASKS", False)
    serial = _moving_frames(pre)
    monkeypatch.setattr(_tasks, "TASKS", True)
    _assert_same_frames(serial, _moving_frames(pre))
    assert serial[-1].info["residual_near_hits"] > 0 and serial[-1].info["direct_rays_cast"] > 0


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_may_block_kernel_equals_the_numpy_tier(seed):
    """The capsule test of ``_may_block`` (numba) equals its numpy specification, including points on the
    source's centre (a zero-length segment) and on the capsule's boundary up to rounding."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(300, 3)) * 2.0
    go = {"center": rng.normal(size=3), "radius": float(rng.uniform(0.1, 1.0)), "reach": float(rng.uniform(0.5, 4))}
    gs = {"center": rng.normal(size=3), "radius": float(rng.uniform(0.1, 1.0))}
    x[0] = gs["center"]
    x[1] = go["center"] + 0.01 * (go["center"] - gs["center"])  # just behind the occluder: it may block
    x[2] = gs["center"] + (gs["center"] - go["center"]) * (go["reach"] + 1.0) / max(
        np.linalg.norm(gs["center"] - go["center"]), 1e-9)  # beyond the source, out of the field's reach
    fast = Interreflection._may_block(x, go, gs)
    ref = Interreflection._may_block(x, go, gs, method="reference")
    assert fast.dtype == bool and fast.shape == (300,)
    assert np.mean(fast == ref) >= 0.99 and fast[1] and not fast[2]


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.sampled_from([0, 1, 63, 64, 65, 300]))
def test_serial_twins_equal_the_parallel_kernels(seed, n):
    """The serial twins the pipeline runs on few items (no parallel region: ``may_block_serial``,
    ``masked_product_serial``, ``_residual._capsule_serial``) give the parallel kernels' arrays bit for bit."""
    from prtlab.interreflection import _kernels, _residual
    from prtlab.interreflection._pipeline import _gaunt_block

    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3)) * 2.0
    centre, source = rng.normal(size=3), rng.normal(size=3)
    radius, reach = float(rng.uniform(0.1, 1.0)), float(rng.uniform(0.5, 4.0))
    serial, parallel = np.empty((2, n), bool)
    _kernels.may_block_serial(x, centre, radius, reach, source, serial)
    _kernels.may_block_kernel(x, centre, radius, reach, source, parallel)
    np.testing.assert_array_equal(serial, parallel)
    spheres = np.c_[rng.normal(size=(3, 3)), rng.uniform(0.05, 0.5, size=3)]
    _residual._capsule_serial(x, source, spheres, radius, 1e-6, serial)
    _residual._capsule_kernel(x, source, spheres, radius, 1e-6, parallel)
    np.testing.assert_array_equal(serial, parallel)
    vis, occ = rng.normal(size=(n, 16)), rng.normal(size=(n + 5, 16))
    rows = rng.permutation(n + 5)[:n].astype(np.int64)
    at = np.flatnonzero(rng.random(n) < 0.7)
    a, b = vis.copy(), vis.copy()
    _kernels.masked_product_serial(a, occ, at, rows, *_gaunt_block(4, 4, 4))
    _kernels.masked_product_kernel(b, occ, at, rows, *_gaunt_block(4, 4, 4))
    np.testing.assert_array_equal(a, b)


def test_threshold_skips_pairs(pre):
    opts = InterreflectionOptions(**QUICK, threshold=1e9)
    res = Interreflection(pre.scene, opts, pre.data).shade(bounces=1)
    assert res.info["skipped_pairs"] == 2
    assert all(np.all(v == 0) for v in res.indirect.values())


def test_api_entry_point(pre, cache_root, monkeypatch):
    monkeypatch.setenv("PRTLAB_CACHE", str(cache_root))  # the fixture's precomputation is a cache hit
    res = shade_scene(pre.scene, bounces=1, progress=False, **QUICK)
    np.testing.assert_allclose(res.total["ball"], pre.shade(bounces=1).total["ball"], rtol=1e-12)
    via_api = prtlab.shade(pre.scene, method="interreflection", bounces=1, progress=False, **QUICK)
    np.testing.assert_allclose(via_api.total["ball"], res.total["ball"], rtol=1e-12)


def test_errors(pre):
    with pytest.raises(ValueError, match="option order must be an int >= 1"):
        InterreflectionOptions(order=0)
    with pytest.raises(ValueError, match="option threshold must be"):
        InterreflectionOptions(threshold=-1.0)
    with pytest.raises(ValueError, match="unknown option"):
        Interreflection.make_options({"n_basiss": 3})
    state = FrameState.from_scene(pre.scene)
    state.lights = [PointLight(position=np.array([0, 3.0, 0]), intensity=np.ones(3))]
    paper = Interreflection(pre.scene, dataclasses.replace(pre.options, shadows="sh"), pre.data)
    with pytest.raises(ValueError, match="not point lights; pass shadows='rays' or 'haar'"):
        paper.shade(state, bounces=1)
    with pytest.raises(ValueError, match="option shadows must be one of 'sh', 'haar', 'rays', got 'wavelet'"):
        InterreflectionOptions(shadows="wavelet")
    with pytest.raises(ValueError, match="option cube_resolution must be a power of two"):
        InterreflectionOptions(cube_resolution=12)


def test_the_papers_options_turn_every_extension_off(pre, cache_root):
    """``PAPER_OPTIONS`` are options of the pipeline, and a frame with the ball moved and an area light shaded with
    them casts no ray (no residual gather, no shadow rays, no near-field rays: the basis radiance interpolated
    everywhere). Each of ``near_field=0.5``, ``residual_rays=64`` and ``shadows="rays"`` added casts rays here."""
    from prtlab.cache import Cache

    assert set(PAPER_OPTIONS) <= {f.name for f in dataclasses.fields(InterreflectionOptions)}
    paper = Interreflection.precompute(pre.scene, {**QUICK, **PAPER_OPTIONS}, cache=Cache(cache_root, progress=False),
                                       progress=False)
    assert all(getattr(paper.options, k) == v for k, v in PAPER_OPTIONS.items())
    state = FrameState.from_scene(paper.scene)
    state.transforms["ball"] = Transform(translate=paper.scene.object("ball").transform.translate + [0.05, 0.0, 0.0])
    state.lights = [*state.lights, AreaLight(center=np.array([0.0, 2.0, 0.0]), u=np.array([0.3, 0.0, 0.0]),
                                             v=np.array([0.0, 0.0, 0.3]), radiance=np.full(3, 5.0))]
    res = paper.shade(state, bounces=2)
    assert res.info["computed_pairs"] > 0
    assert {k: res.info[k] for k in ("residual_rays_cast", "direct_rays_cast", "residual_near_rays_cast")} == \
        {"residual_rays_cast": 0, "direct_rays_cast": 0, "residual_near_rays_cast": 0}
    assert not paper.reuse.near_field
    assert all(np.all(np.isfinite(v)) and np.all(v >= 0) for v in res.total.values())

def test_module_level_precompute(pre, cache_root):
    from prtlab.cache import Cache
    from prtlab.interreflection import precompute

    again = precompute(pre.scene, QUICK, cache=Cache(cache_root, progress=False), progress=False)  # a cache hit
    np.testing.assert_allclose(again.shade(bounces=1).total["ball"], pre.shade(bounces=1).total["ball"], rtol=1e-12)


def test_error_falls_as_the_basis_and_the_order_grow(pre, reference):
    """Indirect error against Monte Carlo (4,096 paths; its own noise 0.085 floor, 0.017 ball) as N (PCA terms,
    order 4) and the SH order (N = 8) grow, by :meth:`Interreflection.truncated` of one precomputation.

    Measured (relative RMS): floor N = 1 / 2 / 4 / 8: 0.999 / 0.961 / 0.356 / 0.313, order 1 / 2 / 3 / 4:
    0.792 / 0.244 / 0.210 / 0.313; ball N: 0.098 / 0.085 / 0.084 / 0.093, order: 0.823 / 0.103 / 0.129 / 0.093.
    The large steps are the ones the paper's choice rests on: the floor's light (the ball's shadow in it)
    needs N >= 4 and every receiver needs order >= 2. Beyond them the error is not monotone, so only the
    overall fall is asserted, with the first big steps. The floor's order-4 step was traced (default fields,
    N = 8): the floor is a plane, so its visibility is exactly 1 and its transfer the exact ``G`` (whose band
    3 is 0): between orders 3 and 4 only the ball's direct light changes, and it improves (on the ball's
    bottom, which the floor sees, 0.90 -> 0.96 of Monte Carlo), yet the floor's bounce light goes from 1.02
    to 1.09 of Monte Carlo; what is left between the two is the N-term fit of the ball's radiance."""
    ref = reference

    def error(p, name):
        a, b = p.shade(bounces=1).indirect[name], ref.indirect[name]
        return float(np.sqrt(np.mean((a - b) ** 2) / np.mean(b**2)))

    import dataclasses

    def paper(p):  # the study is of the basis: no residual gather, which fills in what a small basis misses
        return Interreflection(p.scene, dataclasses.replace(p.options, residual_rays=0), p.data)

    for name in ("floor", "ball"):
        by_n = [error(paper(pre.truncated(n_basis=n)), name) for n in (1, 4, 8)]
        by_order = [error(paper(pre.truncated(order=o)), name) for o in (1, 2, 4)]
        assert by_order[2] < 0.5 * by_order[0] and by_order[1] < 0.5 * by_order[0], (name, by_order)
        assert by_n[2] <= by_n[0], (name, by_n)
        if name == "floor":
            assert by_n[1] < 0.5 * by_n[0] and by_n[2] < 0.5 * by_n[0], by_n


def test_truncated_precomputation(pre):
    small = pre.truncated(n_basis=4, order=3)
    assert small.radiance["ball"].shape[-2:] == (4, 9)
    res = small.shade(bounces=1)
    assert np.all(np.isfinite(res.total["ball"])) and res.indirect["ball"].mean() > 0
    same = pre.truncated()
    np.testing.assert_allclose(same.shade(bounces=1).total["ball"], pre.shade(bounces=1).total["ball"], rtol=1e-12)
    with pytest.raises(ValueError, match=r"order must be an int >= 1 and <= 4 \(at most the precomputed order\)"):
        pre.truncated(order=5)
    with pytest.raises(ValueError, match="n_basis must be an int >= 1, got 0"):
        pre.truncated(n_basis=0)
    with pytest.raises(TypeError, match="n_basis must be an int >= 1, got 2.7 of type float"):
        pre.truncated(n_basis=2.7)


def test_vertices_are_shaded_at_the_shading_points(pre):
    from prtlab.interreflection._pipeline import _local_shading_points

    state = FrameState.from_scene(pre.scene)
    state.transforms["ball"] = Transform(translate=np.array([0.2, 0.9, 0.1]), rotate_deg=np.array([10.0, 30, 0]))
    geo = pre._frame_geometry(state)
    for o in pre.objects:
        np.testing.assert_allclose(geo[o.name]["x"], o.world_shading_points(state.transforms[o.name]), atol=1e-12)
    floor = pre.scene.object("floor")
    assert not np.allclose(_local_shading_points(floor.mesh), floor.mesh.vertices)  # the rim moves inward


def test_near_field_receivers_get_the_ray_cast_basis_radiance(pre):
    """``near_field``: the pair's basis irradiance at near points is <S(x), T> with S cast at x."""
    import dataclasses

    from prtlab.interreflection import basis_irradiance, basis_radiance_at

    far = Interreflection(pre.scene, dataclasses.replace(pre.options, near_field=0.0), pre.data)
    near = Interreflection(pre.scene, dataclasses.replace(pre.options, near_field=100.0), pre.data)
    state = FrameState.from_scene(pre.scene)
    geo = near._frame_geometry(state)
    occ = near._occlusion(geo)
    phi_near, _ = near.basis_irradiance_step(geo, occ)
    phi_far, _ = far.basis_irradiance_step(geo, occ)
    g, floor = geo["ball"], pre.scene.object("floor")
    from prtlab.shadowfields import visibility_pass

    transfer = near._transfer(visibility_pass(g["self"], []), g["g_cos"])
    s = basis_radiance_at(floor.mesh, near.bases["floor"].basis, near.seps["floor"], g["x"], near.options.order,
                          near.options.degree)
    np.testing.assert_allclose(phi_near["ball"]["floor"], np.einsum("vkni,vqi->vqkn", s, transfer), atol=1e-12)
    interpolated = basis_irradiance(pre.radiance["floor"], pre.fields["floor"].grid, g["x"], transfer,
                                    geo["floor"]["T"])
    np.testing.assert_allclose(phi_far["ball"]["floor"], interpolated, atol=1e-12)
    with pytest.raises(ValueError, match="option near_field must be"):
        InterreflectionOptions(near_field=-1.0)
    with pytest.raises(TypeError, match="option pca_occluders must be True or False"):
        InterreflectionOptions(pca_occluders=1)


def test_pca_basis_with_occluders_spans_their_shadows():
    """With as many functions as training lights (+ the mean) every training render is in the span: the
    shadow a box casts on a floor under one of the training lights is reproduced exactly with occluders
    in the training, and not without."""
    from prtlab import pca
    from prtlab.geometry import builtin_mesh
    from prtlab.interreflection._pipeline import _pca_basis

    floor = builtin_mesh("plane", size=[2.0, 2.0], resolution=[12, 12])
    box = builtin_mesh("box", size=[0.4, 0.4, 0.4])
    box_pose = (np.asarray(box.vertices) + [0.0, 0.3, 0.0], np.asarray(box.faces))
    with_shadow = _pca_basis(floor, 5, 4, True, [box_pose])
    without = _pca_basis(floor, 5, 4, True, [])
    import trimesh

    scene_mesh = trimesh.Trimesh(np.concatenate([floor.vertices, box_pose[0]]),
                                 np.concatenate([floor.faces, box_pose[1] + len(floor.vertices)]),
                                 vertex_normals=np.concatenate([floor.vertex_normals, box.vertex_normals]),
                                 process=False)
    lights = pca.pca_light_positions(floor, 4, plane=True)
    shadowed = pca.point_light_intensity(scene_mesh, lights)[:, : len(floor.vertices)]  # (4, V)
    assert np.any(shadowed < pca.point_light_intensity(floor, lights) - 1e-6)  # the box does shadow the floor
    np.testing.assert_allclose(with_shadow.approximate(shadowed), shadowed, atol=1e-10)
    assert np.max(np.abs(without.approximate(shadowed) - shadowed)) > 1e-3


# --------------------------------------------------------------------------- whole scenes against Mitsuba 3
# Fig. 9 (defaults, shadows="haar", after a move) is in the fidelity tier: tests/fidelity/test_interreflection.py.

#: Mitsuba samples per vertex of the room: relative noise at most 0.035 (indirect) and 0.011 (direct,
#: total), within a third of the goals (``Comparison.check``).
ROOM_SPP = 2048
#: (object, part): measured at ROOM_SPP at the defaults (rel_rms, noise) and cause; strict, so a fix fails loudly.
#: Every direct part is within 0.9 % (the ray-traced direct light, ``shadows="rays"``); with the paper's order-4
#: SH direct light (``shadows="sh"``) it was 0.09-0.19 and every total missed.
#: None misses now: the teapot's and bunny's indirect light (0.187, 0.169 with every residual-gather hit
#: interpolated from the floor's vertices under them) are 0.076 and 0.088 with ``residual_near``.
_MEASURED: dict = {}
_KNOWN = {key: f"measured rel_rms {v} (noise {n}): {cause}" for key, (v, n, cause) in _MEASURED.items()}
_ROOM_OBJECTS = ("floor", "wall_back", "wall_left", "box", "teapot", "bunny")


@functools.lru_cache(maxsize=None)
def _mitsuba(name, spp):
    from prtlab.reference import shade_mitsuba

    pytest.importorskip("mitsuba")
    scene = prtlab.load_scene(f"interreflection_{name}")
    return scene, shade_mitsuba(scene, bounces=1, spp=spp, seed=0)


def _whole_scene(name, spp, **options):
    scene, ref = _mitsuba(name, spp)
    ours = Interreflection.precompute(scene, options, progress=False).shade(bounces=1)
    return scene, ours, ref


def _scored(scene, name):
    """Vertices with a meaningful radiance: not the bottoms of objects standing on the floor."""
    obj = scene.object(name)
    if name.startswith(("floor", "wall")):
        return np.ones(obj.n_vertices, bool)
    return obj.world_vertices()[:, 1] > 0.01


def _assert_within_goal(scene, ours, ref, obj, part):
    """``rel_rms <= hypot(goal, noise)`` on the scored vertices, the reference within a third of the goal."""
    comparison = prtlab.compare(ours, ref, objects=[obj], parts=[part], masks={obj: _scored(scene, obj)})
    failures = comparison.check(GOAL[part])
    assert not failures, failures


def _case(obj, part):
    key = (obj, part)
    marks = [pytest.mark.xfail(strict=True, reason=_KNOWN[key])] if key in _KNOWN else []
    return pytest.param(obj, part, marks=marks, id=f"{obj}-{part}")


def test_bounce_pass_equals_the_reference_tier(pre, monkeypatch):
    """Three bounces of the pipeline (weights chained on the PCA sample rows, all bounces in one product), its
    stacked irradiance in float64, equal :func:`reflected_light` (reference tier) bounce by bounce at every vertex
    (float32: ``test_float32_stacked_irradiance_within_its_rounding_bound``)."""
    from prtlab.interreflection import _pipeline, fit_weights, outgoing_radiance, reflected_light

    import dataclasses

    monkeypatch.setattr(_pipeline, "STACKED_IRRADIANCE", np.float64)

    ir = Interreflection(pre.scene, dataclasses.replace(pre.options, residual_rays=0), pre.data)  # the paper's passes
    res = ir.shade(bounces=3)
    state = FrameState.from_scene(pre.scene)
    geo = ir._frame_geometry(state)
    occ = ir._occlusion(geo)
    light_k, _ = ir.direct_step(state, geo, ir.direct_transfer(geo, occ))
    phi, _ = ir.basis_irradiance_step(geo, occ)
    expected = {o.name: 0.0 for o in ir.objects}
    for _ in range(3):
        weights = {o.name: fit_weights(ir.bases[o.name], light_k[o.name], ir.seps[o.name].colour)
                   for o in ir.objects}
        for r in ir.objects:
            sources = [*phi[r.name], r.name]
            lk = reflected_light([*phi[r.name].values(), ir.self_irradiance[r.name]], [weights[s] for s in sources],
                                 method="reference")
            light_k[r.name] = np.maximum(lk, 0.0)
            expected[r.name] = expected[r.name] + outgoing_radiance(light_k[r.name], geo[r.name]["h"],
                                                                    ir.seps[r.name].colour)
    for r in ir.objects:
        np.testing.assert_allclose(res.indirect[r.name], expected[r.name], rtol=1e-10, atol=1e-14)


def test_relighting_reuses_unchanged_area_lights_and_equals_a_fresh_shade(pre):
    """An area light that did not move is not re-projected; one that moved is, and both equal a fresh shade."""
    from prtlab.scene import AreaLight

    sc = pre.scene
    light = AreaLight(center=np.array([0.2, 2.0, 0.1]), u=np.array([0.3, 0, 0]), v=np.array([0, 0, 0.3]),
                      radiance=np.full(3, 5.0))
    state = FrameState.from_scene(sc)
    state.lights = [*sc.lights, light]
    ir = Interreflection(sc, pre.options, pre.data)
    ir.shade(state, bounces=1)
    before = dict(ir.reuse.area_light_sh)
    state.lights = [type(sc.lights[0])(image=sc.lights[0].image * 0.5), light]
    again = ir.shade(state, bounces=1)
    assert all(ir.reuse.area_light_sh[k] is before[k] for k in before)  # reused
    moved = AreaLight(center=np.array([0.0, 2.2, 0.1]), u=light.u, v=light.v, radiance=light.radiance)
    state.lights = [state.lights[0], moved]
    third = ir.shade(state, bounces=1)
    assert all(ir.reuse.area_light_sh[k] is not before[k] for k in before)  # recomputed
    for res, lights in ((again, [state.lights[0], light]), (third, state.lights)):
        fresh_state = FrameState.from_scene(sc)
        fresh_state.lights = list(lights)
        fresh = Interreflection(sc, pre.options, pre.data).shade(fresh_state, bounces=1)
        for name in ("floor", "ball"):
            np.testing.assert_allclose(res.total[name], fresh.total[name], rtol=1e-12, atol=1e-15)


@pytest.fixture(scope="module")
def room_scene():
    return _whole_scene("room", ROOM_SPP)


@pytest.mark.slow
@pytest.mark.mitsuba
@pytest.mark.parametrize("obj, part", [_case(o, p) for o in _ROOM_OBJECTS for p in GOAL])
def test_room_against_mitsuba(room_scene, obj, part):
    """A room of several objects (floor, two walls, box, teapot, bunny), one bounce, defaults, against
    Mitsuba at ``ROOM_SPP``: every object, direct / indirect / total within the goals."""
    _assert_within_goal(*room_scene, obj, part)


def test_threshold_skips_a_far_object_and_its_skipped_light_is_below_the_bound(pre):
    """Sec. 5.4 with a real threshold: a ball 30 units away. Its pairs (both ways) have an ``I_c`` far
    below the near pairs'; a threshold between them skips exactly those four pairs, and the basis
    irradiance they would have given is below ``I_c (d / (d - R_r))^2`` at every receiver vertex
    (:meth:`Interreflection.pair_importance`; 5 % on top for the SH truncation of both sides)."""
    import dataclasses

    from prtlab.scene import SceneObject

    base = pre.scene
    far = SceneObject("far", base.object("ball").mesh, Transform(translate=np.array([30.0, 0.7, 0.0])),
                      base.object("ball").material)
    sc = type(base)(objects=[*base.objects, far], lights=base.lights, camera=base.camera)
    data = {**pre.data, "far": pre.data["ball"]}
    full = Interreflection(sc, pre.options, data)
    state = FrameState.from_scene(sc)
    geo = full._frame_geometry(state)
    occ = full._occlusion(geo)
    phi, _ = full.basis_irradiance_step(geo, occ)
    imp = {(r.name, s.name): full.pair_importance(geo, r, s) for r in full.objects for s in full.objects if r is not s}
    far_pairs = {k for k in imp if "far" in k}
    assert max(imp[k] for k in far_pairs) < 1e-2 * min(imp[k] for k in imp if k not in far_pairs)
    threshold = np.sqrt(max(imp[k] for k in far_pairs) * min(imp[k] for k in imp if k not in far_pairs))
    assert threshold > 0
    cut = Interreflection(sc, dataclasses.replace(pre.options, threshold=float(threshold)), data)
    res = cut.shade(state, bounces=1)
    assert res.info["skipped_pairs"] == 4 and res.info["computed_pairs"] == 2, (res.info, imp, threshold, cut.options)
    for r_name, s_name in far_pairs:
        gr, gs = geo[r_name], geo[s_name]
        d = np.linalg.norm(gs["center"] - gr["center"])
        radius = np.max(np.linalg.norm(gr["x"] - gr["center"], axis=1))
        bound = imp[r_name, s_name] * (d / (d - radius)) ** 2
        assert np.max(np.abs(phi[r_name][s_name])) <= 1.05 * bound
    np.testing.assert_array_equal(res.indirect["far"], 0.0)


def test_moving_an_occluder_reuses_the_near_field_basis_radiance(pre):
    """A second ball near the first moves: the pairs whose visibility it touches are recomputed, but the
    basis radiance cast at the first ball's vertices from the floor (their relative pose is unchanged) is
    reused; the result equals a from-scratch shade."""
    from prtlab.scene import SceneObject

    base = pre.scene
    other = SceneObject("other", base.object("ball").mesh, Transform(translate=np.array([1.3, 0.7, 0.0])),
                        base.object("ball").material)
    sc = type(base)(objects=[*base.objects, other], lights=base.lights, camera=base.camera)
    data = {**pre.data, "other": pre.data["ball"]}
    ir = Interreflection(sc, pre.options, data)
    state = FrameState.from_scene(sc)
    ir.shade(state, bounces=1)
    before = dict(ir.reuse.near_field)
    assert any(len(near) for near, _ in before.values())
    state.transforms["other"] = Transform(translate=np.array([1.4, 0.7, 0.2]))
    moved = ir.shade(state, bounces=1)
    # the four pairs of "other" are recomputed; between floor and ball only the points it may shadow
    assert moved.info["computed_pairs"] == 4 and moved.info["updated_pairs"] == 2
    assert 0 < moved.info["updated_rows"] < sum(o.n_vertices for o in sc.objects if o.name != "other")
    kept = [k for k in before if ir.reuse.near_field.get(k) is before[k]]
    assert any(k[0] == "floor" and len(before[k][0]) for k in kept)  # the ball's near points under the floor
    fresh = Interreflection(sc, pre.options, data).shade(state, bounces=1)
    for name in ("floor", "ball", "other"):
        np.testing.assert_allclose(moved.total[name], fresh.total[name], rtol=1e-12, atol=1e-15)


def test_haar_shadows_light_by_a_point_light_with_a_sharp_shadow():
    """``shadows="haar"``: point lights work, and the ball's shadow on the floor is what the shadow field's
    contract gives, from the closed form of the sphere. The unshadowed irradiance is exact, so
    ``ours / unshadowed`` is the visibility toward the light: the trilinear blend of the 8 surrounding
    samples of the ball's field, each read bilinearly between the 4 texel centres around the light's
    direction (``prtlab.shadowfields._haar_direct``), each texel the ray through its centre. Those rays are
    cast here against the sphere: a ray missing the ball's circumscribed sphere (radius 0.5) misses the
    icosphere, one within its inradius hits it, so the visibility lies between the two blends (equal
    unless a ray grazes the tessellation); it is exactly 1 where every blended ray misses and 0 where every
    one hits. The 256 Haar coefficients kept hold each sample's cubemap exactly here, or this fails."""
    from prtlab.geometry import cubemap_directions, direction_to_cubemap
    from prtlab.shadowfields import sphere_grid

    s = ball_over_floor()
    s.lights = [PointLight(position=np.array([0.4, 2.5, 0.3]), intensity=np.array([4.0, 4.0, 4.0]))]
    res_cube = 16
    pre = Interreflection.precompute(s, dict(QUICK, shadows="haar", cube_resolution=res_cube, haar_keep=256),
                                     cache=False, progress=False)
    res = pre.shade(bounces=0)
    floor, ball = s.object("floor"), s.object("ball")
    x, n = floor.world_shading_points(), floor.world_normals()
    to_light = s.lights[0].position - x
    r = np.linalg.norm(to_light, axis=1)
    d = to_light / r[:, None]
    unshadowed = 0.8 / np.pi * 4.0 * np.maximum(np.sum(n * d, axis=1), 0.0) / r**2
    visibility = res.direct["floor"][:, 0] / unshadowed
    # the 8 samples of the ball's field (its grid, object space: the ball is only translated) ...
    grid = sphere_grid(ball.mesh, QUICK["n_radii"], QUICK["resolution"])
    corners, w, beyond = grid.trilinear_corners(x - ball.transform.translate)
    assert not beyond.any()
    samples = grid.points().reshape(-1, 3)[corners]  # (V, 8, 3), ball centre at the origin
    # ... and the 4 texel centres around d on its face (texel centres at (j + 1/2) / res, clamped at borders)
    face, fs, ft = direction_to_cubemap(d)
    cx, cy = np.clip(fs * res_cube - 0.5, 0, res_cube - 1), np.clip(ft * res_cube - 0.5, 0, res_cube - 1)
    j0 = np.minimum(np.floor(cx).astype(np.int64), res_cube - 2)
    i0 = np.minimum(np.floor(cy).astype(np.int64), res_cube - 2)
    fx, fy = cx - j0, cy - i0
    centres = cubemap_directions(res_cube)
    texels = np.stack([centres[face, i0 + a, j0 + b] for a in (0, 1) for b in (0, 1)], axis=1)  # (V, 4, 3)
    bw = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], axis=1)
    along = np.einsum("vcx,vtx->vct", samples, texels)
    miss_dist = np.linalg.norm(samples[:, :, None] - along[..., None] * texels[:, None], axis=-1)
    v, f = ball.mesh.vertices, ball.mesh.faces
    normal = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    inradius = np.min(np.abs(np.sum(normal * v[f[:, 0]], axis=1)) / np.linalg.norm(normal, axis=1))
    misses = ~((along < 0) & (miss_dist < 0.5))
    hits = (along < 0) & (miss_dist < inradius)
    weight = w[:, :, None] * bw[:, None, :]
    low, high = np.sum(weight * misses, axis=(1, 2)), np.sum(weight * ~hits, axis=(1, 2))
    assert np.all((visibility >= low - 1e-9) & (visibility <= high + 1e-9)), np.max(
        np.maximum(low - visibility, visibility - high))
    used = weight > 0
    lit, umbra = np.all(misses | ~used, axis=(1, 2)), np.all(hits | ~used, axis=(1, 2))
    assert lit.sum() > 50 and umbra.sum() > 0 and np.sum(high - low > 0) < 0.1 * len(x)
    np.testing.assert_allclose(visibility[lit], 1.0, atol=1e-9)
    np.testing.assert_allclose(visibility[umbra], 0.0, atol=1e-9)
    np.testing.assert_allclose(res.direct["floor"], res.direct["floor"][:, :1] * [1, 1, 1], rtol=1e-12)


def floor_and_wall(left_wall=False):
    """A floor and one wall meeting at a right angle (the room's back corner) under the room's light;
    with ``left_wall`` also the room's left wall (a second edge with the floor, one with the wall)."""
    from prtlab.scene import Scene

    left = [{"name": "wall_left", "mesh": {"builtin": "plane", "size": [2, 4], "resolution": [6, 12]},
             "transform": {"translate": [-2, 1, 0], "rotate_deg": [0, 0, -90]},
             "material": {"type": "diffuse", "albedo": [0.75, 0.25, 0.2]}}] if left_wall else []
    return Scene.from_dict({
        "objects": [
            {"name": "floor", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [12, 12]},
             "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
            {"name": "wall", "mesh": {"builtin": "plane", "size": [4, 2], "resolution": [12, 6]},
             "transform": {"translate": [0, 1, -2], "rotate_deg": [90, 0, 0]},
             "material": {"type": "diffuse", "albedo": [0.3, 0.7, 0.3]}},
            *left,
        ],
        "lights": [{"type": "area", "center": [0, 2.6, 0], "u": [0.4, 0, 0], "v": [0, 0, 0.4],
                    "radiance": [20, 20, 20]}],
        "camera": {"position": [1.5, 2.0, 3.5], "look_at": [-0.3, 0.4, -0.5]},
    })


def test_planes_meeting_at_an_edge_get_their_bounce_light(cache_root):
    """The rows of a floor and a wall that lie on the other plane are lit in the PCA training renders.

    With ``pca_occluders`` the training shadow rays left the vertices: those of the shared edge lie
    on the other plane, every ray grazed it, the row was dark in all renders and the basis exactly 0
    there; as a source the edge then emitted nothing, and the light bouncing between the planes (most
    of it from near the edge) was 14 % (floor) and 14 % (wall) too dark on average, 0.02x on the edge
    rows. From the shading points (as the pipeline shades) the means are within 1 % of Monte Carlo.
    Per-object means held to the indirect goal by :func:`mean_bound` (128 paths).
    """
    from prtlab.cache import Cache

    pre = Interreflection.precompute(floor_and_wall(), QUICK, cache=Cache(cache_root, progress=False),
                                     progress=False)
    for name, axis, at in (("floor", 2, -2.0), ("wall", 1, 0.0)):
        edge = np.abs(pre.scene.object(name).world_vertices()[:, axis] - at) < 1e-9
        assert edge.sum() == 13 and np.all(pre.entries[name]["pca_basis"][0][edge] > 0)  # the mean render is lit
    res = pre.shade(bounces=1)
    ref = path_trace(pre.scene, 1, 128, np.random.default_rng(5))
    for name in ("floor", "wall"):
        err, bound = mean_bound(res.indirect[name], ref.indirect[name], ref.stderr["indirect"][name], GOAL["indirect"])
        assert np.all(err <= bound), (name, err, bound)


def test_a_plane_that_blocks_nothing_between_two_others_is_not_their_occluder(cache_root, monkeypatch):
    """A floor, a back wall and a left wall (the room without its objects), one bounce.

    The basis irradiance of a pair took every other object as an occluder: the left wall's
    visibility at a back-wall point is a half-space, and its order-4 SH product with the floor's
    radiance leaked onto the floor's directions. Measured (128 paths) on these planes: mean indirect
    0.91 (floor), 0.88 (back wall), 0.86 (left wall) of Monte Carlo; on the room's finer planes
    0.96 / 0.92 / 0.91. A flat object with the receiver and the source on one side of its plane is
    now left out (``Interreflection._plane_separates``): exactly the shade with no occluders at all
    here (its basis irradiance; indirect 0.96 / 0.97 / 0.95, room planes 1.00 / 1.00 / 1.00), per-object
    means held to the indirect goal by :func:`mean_bound` (128 paths). A plane between the two
    still blocks.
    """
    from prtlab.cache import Cache

    pre = Interreflection.precompute(floor_and_wall(left_wall=True), QUICK, cache=Cache(cache_root, progress=False),
                                     progress=False)
    ours = pre.shade(bounces=1)
    ref = path_trace(pre.scene, 1, 128, np.random.default_rng(5))
    geo = pre._frame_geometry(FrameState.from_scene(pre.scene))
    phi, _ = Interreflection(pre.scene, pre.options, pre.data).basis_irradiance_step(geo, pre._occlusion(geo))
    monkeypatch.setattr(Interreflection, "_blockers", lambda self, geo, r, s: [])
    free, _ = Interreflection(pre.scene, pre.options, pre.data).basis_irradiance_step(geo, pre._occlusion(geo))
    for name in ("floor", "wall", "wall_left"):
        for source in phi[name]:
            np.testing.assert_allclose(phi[name][source], free[name][source], rtol=1e-10, atol=1e-14)
        err, bound = mean_bound(ours.indirect[name], ref.indirect[name], ref.stderr["indirect"][name],
                                GOAL["indirect"])
        assert np.all(err <= bound), (name, err, bound)
    floor, wall, left = (pre.scene.object(n) for n in ("floor", "wall", "wall_left"))
    assert pre._plane_separates(geo, left, wall, floor) and pre._plane_separates(geo, wall, left, floor)
    # a plane between receiver and source: the floor's plane with the wall's half below it
    state = FrameState.from_scene(pre.scene)
    state.transforms["wall"] = Transform(translate=np.array([0.0, 0.0, -2.0]), rotate_deg=np.array([90.0, 0.0, 0.0]))
    assert not pre._plane_separates(pre._frame_geometry(state), floor, wall, left)


def test_area_lights_from_source_radiance_fields_match_the_exact_projection(pre):
    """``area_lights="field"``: one field per light shape, shared by moved, turned and scaled lights, sized
    like the objects' sample spheres. Its direct light converges to the exact projection's as the spheres
    refine: halving the spacing (8 x 6 x 8 x 8 to 16 x 6 x 16 x 16) cuts the relative L2 error per object at
    least to half (trilinear interpolation errs like the spacing squared: a quarter). Measured, floor /
    ball: 0.169 / 0.153 on the quick spheres, 0.034 / 0.028 on the default ones."""
    import dataclasses

    from prtlab.scene import AreaLight

    sc = pre.scene
    paper = dataclasses.replace(pre.options, shadows="sh")  # the option of the SH direct light
    exact = Interreflection(sc, paper, pre.data)
    light = AreaLight(center=np.array([0.2, 2.0, 0.1]), u=np.array([0.3, 0, 0]), v=np.array([0, 0, 0.3]),
                      radiance=np.full(3, 5.0))
    R = Transform(rotate_deg=np.array([20.0, 30.0, 0.0])).rotation
    turned = AreaLight(center=np.array([-0.3, 1.8, 0.2]), u=1.5 * R @ light.u, v=1.5 * R @ light.v,
                       radiance=np.array([1.0, 2.0, 3.0]))
    # the objects' fields are precomputed: at run time n_radii and resolution size only the light's field
    errors = []
    for spheres in ({}, {"n_radii": 16, "resolution": 16}):
        field = Interreflection(sc, dataclasses.replace(paper, area_lights="field", **spheres), pre.data)
        errors.append({})
        for i, lit in enumerate((light, turned)):
            state = FrameState.from_scene(sc)
            state.lights = [lit]
            a, b = exact.shade(state, bounces=0), field.shade(state, bounces=0)
            for name in ("floor", "ball"):
                errors[-1][i, name] = np.linalg.norm(b.direct[name] - a.direct[name]) / np.linalg.norm(a.direct[name])
        assert len(field.reuse.source_fields) == 1  # the turned light is a uniform scale of the first
    assert all(errors[1][k] <= 0.5 * errors[0][k] for k in errors[0]), errors
    with pytest.raises(ValueError, match="option area_lights must be one of 'exact', 'field'"):
        InterreflectionOptions(area_lights="srf")


# ------------------------------------------------------------------ order-independent occlusion (occlusion="exp")


def _two_balls(pre, **options):
    """The quick scene with a second ball touching the first (arrays shared with it), ``options`` replaced; the
    first ball's frame geometry and occlusion lookups, and its rows that the floor's and the other ball's fields
    both reach."""
    import dataclasses

    from prtlab.scene import SceneObject

    base = pre.scene
    other = SceneObject("other", base.object("ball").mesh, Transform(translate=np.array([0.95, 0.7, 0.2])),
                        base.object("ball").material)
    sc = type(base)(objects=[*base.objects, other], lights=base.lights, camera=base.camera)
    ir = Interreflection(sc, dataclasses.replace(pre.options, **options), {**pre.data, "other": pre.data["ball"]})
    geo = ir._frame_geometry(FrameState.from_scene(sc))
    occ = ir._occlusion(geo)
    g = geo["ball"]
    both = np.flatnonzero(ir._within_reach(g["x"], geo["floor"]) & ir._within_reach(g["x"], geo["other"]))
    return ir, g, occ["ball"], both


def test_log_occlusion_field_round_trips_and_is_zero_beyond(pre):
    """``exp*`` (exact tier) of the log field gives back ``floor 1 + (1 - floor) O`` at every sample, within the
    Newton tolerance (1e-6 relative; its rule of degree 31 against the exact tier's 80); beyond the outermost
    sphere the log lookup is 0, the log of the unoccluded 1."""
    from prtlab import sh
    from prtlab.shadowfields import LOG_FLOOR, log_occlusion_field

    field = Interreflection(pre.scene, pre.options, pre.data).fields["ball"]
    logs = log_occlusion_field(field)
    coeffs = field.coeffs.reshape(-1, 16)
    target = (1.0 - LOG_FLOOR) * coeffs
    target[:, 0] += LOG_FLOOR * np.sqrt(4.0 * np.pi)
    back = sh.exp(logs.coeffs.reshape(-1, 16), method="exact", channels=False)
    assert np.all(np.linalg.norm(back - target, axis=1) <= 1e-5 * np.linalg.norm(target, axis=1))
    far = field.grid.center + np.array([[0.0, 0.0, 1.01 * field.grid.radii[-1]]])
    np.testing.assert_array_equal(logs.lookup(far), 0.0)
    assert logs.lookup(far).shape == (1, 16) and field.lookup(far)[0, 0] == np.sqrt(4.0 * np.pi)


def test_exp_occlusion_does_not_depend_on_the_occluders_order(pre):
    """Two touching balls over the floor: at the first ball's points (its self-visibility not constant) with the
    floor and the other ball as occluders, the visibility of the SH products changes with their order (products
    truncated to order n do not commute), that of ``occlusion="exp"`` does not (one sum of logs, in either order:
    within its rounding)."""
    for occlusion, same in (("product", False), ("exp", True)):
        ir, g, occ_r, both = _two_balls(pre, occlusion=occlusion)
        assert len(both) > 10
        masks = np.ones(len(both), bool)
        one = ir._visibility(g, occ_r, [("floor", masks), ("other", masks)], both)
        two = ir._visibility(g, occ_r, [("other", masks), ("floor", masks)], both)
        gap = np.max(np.abs(one - two))
        if same:
            assert gap <= 1e-12 * np.max(np.abs(one)), gap
        else:
            assert gap > 1e-6 * np.max(np.abs(one)), gap


def test_exp_occlusion_of_one_occluder_with_the_exact_exponential_is_its_floored_visibility(pre):
    """One occluder through ``exp*`` (exact tier) of its looked-up log is its floored visibility ``floor 1 + (1 -
    floor) O``, within Newton's tolerance, where the lookups are not interpolated between samples: at the sample
    points of the ball's field, posed as in the scene."""
    from prtlab import sh
    from prtlab.shadowfields import LOG_FLOOR

    ir, _, _, _ = _two_balls(pre, occlusion="exp", exp_method="exact")
    field, logs = ir.fields["ball"], ir.occluders["ball"]
    points = field.grid.points().reshape(-1, 3)[:: 7] + pre.scene.object("ball").transform.translate
    exact = sh.exp(logs.lookup(points, pre.scene.object("ball").transform), method="exact", channels=False)
    floored = (1.0 - LOG_FLOOR) * field.lookup(points, pre.scene.object("ball").transform)
    floored[:, 0] += LOG_FLOOR * np.sqrt(4.0 * np.pi)
    assert np.all(np.linalg.norm(exact - floored, axis=1) <= 1e-5 * np.linalg.norm(floored, axis=1))


def test_exp_occlusion_logs_are_stored_by_its_precomputation(pre, cache_root, monkeypatch):
    """A precomputation made with ``occlusion="exp"`` is a cache entry of its own that stores every object's log
    field (the logs of its occlusion field, bit for bit); a pipeline built from it reads them and computes none,
    and its lower-order truncation drops them (a log's lower bands are not the lower bands' log)."""
    from prtlab.cache import Cache, cache_key
    from prtlab.interreflection import _pipeline
    from prtlab.shadowfields import log_occlusion_field

    options = {**QUICK, "occlusion": "exp"}
    assert (cache_key(*Interreflection.cache_key_parts(pre.scene, Interreflection.make_options(options)))
            != cache_key(*Interreflection.cache_key_parts(pre.scene, pre.options)))
    ours = Interreflection.precompute(pre.scene, options, cache=Cache(cache_root, progress=False), progress=False)
    for o in ours.objects:
        np.testing.assert_array_equal(ours.occluders[o.name].coeffs, log_occlusion_field(ours.fields[o.name]).coeffs)

    def refuse(field):
        raise AssertionError("a stored log field was computed again")

    monkeypatch.setattr(_pipeline, "log_occlusion_field", refuse)
    again = Interreflection(ours.scene, ours.options, ours.data)
    assert all(again.occluders[o.name].log for o in again.objects)
    with pytest.raises(AssertionError, match="computed again"):
        ours.truncated(order=ours.options.order - 1)


def test_exp_occlusion_shades_close_to_the_products(pre):
    """The whole quick scene with ``occlusion="exp"`` (HYB) against the products: the floor and the ball differ by
    less than the total's goal (5 % relative RMS, GOAL): a sanity bound; the option's accuracy against Mitsuba is
    scored in the fidelity tier (``test_cluster_against_mitsuba``)."""
    import dataclasses

    base = Interreflection(pre.scene, pre.options, pre.data).shade(bounces=1)
    ours = Interreflection(pre.scene, dataclasses.replace(pre.options, occlusion="exp"), pre.data).shade(bounces=1)
    for name in ("floor", "ball"):
        a, b = base.total[name], ours.total[name]
        assert np.sqrt(np.mean((a - b) ** 2)) <= GOAL["total"] * np.sqrt(np.mean(a**2)), name


def test_kept_visibility_prefix_equals_the_whole_product(pre):
    """``_visibility(keep=)`` (the partial product of the factors before the first changed field, kept per row)
    against the whole product, bit for bit, through calls where a field changes (its pose), rows come and go,
    masks change at some rows, the factors' order or set changes and the receiver moves."""
    from prtlab.interreflection._pipeline import OcclusionFields

    rng = np.random.default_rng(3)
    n_v, n2 = 700, pre.options.order ** 2
    names = ["a", "b", "c", "d", "e"]
    occ = OcclusionFields(names, rng.normal(size=(len(names), n_v, n2)))
    occ.poses = [("r0", name, 0) for name in names]
    g = {"self": rng.normal(size=(n_v, n2)), "pose": ("r0",), "x": np.zeros((n_v, 3))}
    masks = {name: rng.random(n_v) < 0.8 for name in names}
    ir = Interreflection(pre.scene, pre.options, pre.data)

    def call(order, rows, expect_kept=None):
        rows = np.asarray(rows, np.int64)
        factors = [(name, masks[name][rows]) for name in order]
        whole = ir._visibility(g, occ, factors, rows)
        kept = ir._visibility(g, occ, factors, rows, keep=("test",))
        assert np.array_equal(kept, whole)
        if expect_kept is not None:
            prefix = ir.reuse.visibility_prefix[("test",)]["prefix"]
            assert (0 if prefix is None else len(prefix["fields"])) == expect_kept

    def move(name, pose):
        i = occ.index[name]
        occ.fields[i] = rng.normal(size=(n_v, n2))
        occ.poses[i] = ("r0", name, pose)

    every = np.arange(n_v)
    call(names, every, 0)
    call(names, every, 5)  # nothing changed: the whole product kept
    move("c", 1)
    call(names, rng.choice(n_v, 300, replace=False), 2)  # "c" moved: "a" and "b" kept
    move("c", 2)
    call(names, rng.choice(n_v, 400, replace=False), 2)  # rows kept and rows new
    masks["a"][::7] = ~masks["a"][::7]  # masks changed at some rows: those make the product again
    move("c", 3)
    call(names, every, 2)
    move("a", 1)
    call(names, every, 0)
    call(["b", "a", "e"], every[::2], 0)  # another order
    move("e", 1)
    call(["b", "a", "e"], every[::3], 2)
    call(["b", "a"], every[::3], 2)
    g["pose"] = ("r1",)  # the receiver moved: its self-visibility is new
    g["self"] = rng.normal(size=(n_v, n2))
    call(["b", "a"], every, 0)


@pytest.fixture(scope="module")
def balls_in_a_row(cache_root):
    """A floor and four small balls in a row over it (the quick settings): the pairs along the row have the
    balls between them as occluders, several of them before the one that moves."""
    from prtlab.cache import Cache
    from prtlab.scene import Scene

    objects = [{"name": "floor", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [8, 8]},
                "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}}]
    for i in range(4):
        objects.append({"name": f"ball{i}", "mesh": {"builtin": "icosphere", "radius": 0.3, "subdivisions": 2},
                        "transform": {"translate": [-1.2 + 0.8 * i, 0.5, 0.1 * i]}, "dynamic": True,
                        "material": {"type": "diffuse", "albedo": [0.5 + 0.1 * i, 0.6, 0.7]}})
    scene = Scene.from_dict({"objects": objects, "lights": [
        {"type": "environment", "sky": {"sun_elevation_deg": 40, "sun_azimuth_deg": 30, "turbidity": 3},
         "scale": 0.1}], "camera": {"position": [0, 3, 6], "look_at": [0, 0, 0]}})
    return Interreflection.precompute(scene, QUICK, cache=Cache(cache_root, progress=False), progress=False)


def test_frames_that_move_objects_equal_a_fresh_pipeline_per_frame(balls_in_a_row):
    """One pipeline through frames that move balls (one a little at a time, as ``move_one`` does, then another,
    then both, then back) against a fresh pipeline per frame: every object's direct, indirect and total light
    equal bit for bit (the kept visibility products follow the fields, masks and rows that change); the kept
    products are taken."""
    pre = balls_in_a_row
    base = {o.name: o.transform for o in pre.objects}

    def at(name, dx, dy=0.0):
        t = base[name]
        return Transform(translate=t.translate + [dx, dy, 0.0], rotate_deg=t.rotate_deg, scale=t.scale)

    frames = [{}, {"ball2": at("ball2", 0.02)}, {"ball2": at("ball2", 0.04)}, {"ball2": at("ball2", 0.3, 0.2)},
              {"ball1": at("ball1", -0.05)}, {"ball1": at("ball1", -0.05), "ball2": at("ball2", 0.05)},
              {"ball1": at("ball1", 0.1, 0.1), "ball2": at("ball2", 0.05)}, {}]
    kept = Interreflection(pre.scene, pre.options, pre.data)
    taken = 0
    for moves in frames:
        state = FrameState.from_scene(pre.scene)
        state.transforms.update(moves)
        fresh = Interreflection(pre.scene, pre.options, pre.data).shade(state, bounces=2)
        got = kept.shade(state, bounces=2)
        for name in got.total:
            for part in ("direct", "indirect", "total"):
                assert np.array_equal(getattr(got, part)[name], getattr(fresh, part)[name]), (moves, name, part)
        taken += sum(e["prefix"] is not None for e in kept.reuse.visibility_prefix.values())
    assert taken > 0
