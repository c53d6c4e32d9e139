"""Tests of prtlab.geometry._embree: the ctypes Embree 4 engine of RayCaster against the embreex path and
the float64 brute force, its thread-count independence, its fallback and the lifetime of its scenes."""

from __future__ import annotations

import gc
import os
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest
import trimesh
from hypothesis import given
from hypothesis import strategies as st

from prtlab.geometry import RayCaster, _embree
from prtlab.scene import Transform
from tests.conftest import random_directions

#: float32 unit roundoff: Embree rounds origins, directions and vertices to float32 once each.
U32 = 2.0**-24

#: Rounding errors allowed, in units of ``U32 * scale`` (``scale`` = largest origin + distance + vertex
#: magnitude): three coordinates rounded in each of origin, direction and vertex, plus Embree's own few
#: operations; 16 leaves a margin of about two.
ROUNDING_UNITS = 16.0


def _random_scene(rng):
    """Closed meshes (shared edges), a box and an open two-triangle sheet, each randomly placed."""
    sphere = trimesh.creation.icosphere(subdivisions=int(rng.integers(1, 3)))
    sphere.vertices *= rng.uniform(0.5, 1.5, size=3)
    box = trimesh.creation.box(extents=rng.uniform(0.2, 1.0, size=3))
    sheet = (np.array([[-1.0, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]]), np.array([[0, 1, 2], [0, 2, 3]]))
    meshes = [sphere, box, sheet]
    transforms = [Transform(translate=rng.normal(size=3), rotate_deg=rng.uniform(0, 90, 3)) for _ in meshes]
    return RayCaster(meshes, transforms)


def _random_rays(rng, n, caster):
    """Origins around the scene; half the rays aimed near a random vertex, a third with a finite tmax."""
    origins = rng.normal(size=(n, 3)) * 3.0
    dirs = random_directions(rng, n)
    verts = np.concatenate([caster.world_vertices(i) for i in range(caster.n_objects)])
    aim = verts[rng.integers(0, len(verts), n // 2)] + 0.2 * rng.normal(size=(n // 2, 3))
    dirs[: n // 2] = aim - origins[: n // 2]
    tmax = np.where(rng.random(n) < 0.3, rng.uniform(0.5, 6.0, n), np.inf)
    return origins, dirs, tmax


def _scale(caster, origins, hits_list):
    """Magnitude that float32 rounding is relative to: largest |origin| + distance + |vertex|."""
    dist = max([np.max(h.distance[h.hit], initial=0.0) for h in hits_list])
    verts = max(np.max(np.abs(caster.world_vertices(i))) for i in range(caster.n_objects))
    return float(np.max(np.linalg.norm(origins, axis=1)) + dist + verts)


def _edge_distance(caster, hits, rays):
    """For each hit in ``rays`` (indices): distance of its float64 hit point to the nearest edge of its
    triangle, times ``|n . d|`` (a ray moved by ``delta`` moves its hit point by up to ``delta / |n . d|``)."""
    out = np.empty(len(rays))
    for j, i in enumerate(rays):
        tri = caster.world_vertices(hits.object[i])[caster.faces(hits.object[i])[hits.triangle[i]]]
        p = hits.point[i]
        best = np.inf
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            s = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
            best = min(best, np.linalg.norm(p - (a + s * (b - a))))
        out[j] = best
    return out


def _agree_up_to_float32_rounding(caster, origins, dirs, a, b, max_fraction):
    """Hits of ``a`` and ``b`` agree ray by ray except within float32 rounding of an edge: where they
    differ (hit / miss, or another face), the nearer of the two hits lies that close to an edge of its
    triangle (the other engine slipped past that edge or grazed it). At most ``max_fraction`` of the rays
    may differ; distances of the same face agree to float32 rounding. Returns how many differ."""
    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    tol = ROUNDING_UNITS * U32 * _scale(caster, origins, [a, b])
    same_face = a.hit & b.hit & (a.object == b.object) & (a.triangle == b.triangle)
    odd = np.flatnonzero((a.hit | b.hit) & ~same_face)
    a_first = a.distance[odd] <= b.distance[odd]
    for hits, rays in ((a, odd[a_first]), (b, odd[~a_first])):
        cos = np.abs(np.sum(hits.normal[rays] * unit[rays], axis=1))
        near = _edge_distance(caster, hits, rays) * cos
        assert np.all(near <= tol), f"rays {rays[near > tol]} differ away from every edge"
    assert len(odd) <= max_fraction * len(origins)
    cos = np.abs(np.sum(a.normal[same_face] * unit[same_face], axis=1))
    assert np.all(np.abs(a.distance[same_face] - b.distance[same_face]) * cos <= tol)
    return len(odd)


# -------------------------------------------------------------- engines against each other


@given(seed=st.integers(0, 2**31 - 1))
def test_engine_matches_embreex_ray_by_ray(seed):
    """Same library, robust flag and float32 rays: the hits are those of embreex's ``run``, bit for bit."""
    rng = np.random.default_rng(seed)
    caster = _random_scene(rng)
    origins, dirs, tmax = _random_rays(rng, 300, caster)
    ours = caster.closest_hit(origins, dirs, tmax)
    theirs = caster.closest_hit(origins, dirs, tmax, method="embreex")
    for field in ("hit", "object", "triangle", "barycentric", "distance"):
        np.testing.assert_array_equal(getattr(ours, field), getattr(theirs, field), err_msg=field)
    np.testing.assert_array_equal(caster.occluded(origins, dirs, tmax),
                                  caster.occluded(origins, dirs, tmax, method="embreex"))
    assert 0.1 < ours.hit.mean() < 0.9


@given(seed=st.integers(0, 2**31 - 1))
def test_engine_matches_float64_brute_force_up_to_float32_rounding(seed):
    rng = np.random.default_rng(seed)
    caster = _random_scene(rng)
    origins, dirs, tmax = _random_rays(rng, 300, caster)
    ours = caster.closest_hit(origins, dirs, tmax)
    ref = caster.closest_hit(origins, dirs, tmax, method="numpy")
    _agree_up_to_float32_rounding(caster, origins, dirs, ours, ref, max_fraction=0.01)
    occluded = caster.occluded(origins, dirs, tmax)
    np.testing.assert_array_equal(occluded, ours.hit)  # Embree's any-hit and closest-hit share one test


def test_rays_at_shared_edges_are_the_only_disagreements(rng):
    """Rays through the shared edges of a closed mesh, entering it across both faces: Embree's watertight
    test hits one of the two faces (no ray slips through); every disagreement with the float64 brute force
    lies within float32 rounding of an edge."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    caster = RayCaster([mesh])
    edges = mesh.vertices[mesh.face_adjacency_edges]
    targets = edges[:, 0] + rng.uniform(0.2, 0.8, size=(len(edges), 1)) * (edges[:, 1] - edges[:, 0])
    origins = targets + 2.0 * random_directions(rng, len(targets))
    dirs = targets - origins
    normals = mesh.face_normals[mesh.face_adjacency]  # (n_edges, 2, 3)
    entering = np.all(np.einsum("ekj,ej->ek", normals, dirs) < -0.05 * np.linalg.norm(dirs, axis=1)[:, None], axis=1)
    origins, dirs = origins[entering], dirs[entering]
    assert len(origins) > 100
    ours = caster.closest_hit(origins, dirs)
    assert ours.hit.all()
    ref = caster.closest_hit(origins, dirs, method="numpy")
    _agree_up_to_float32_rounding(caster, origins, dirs, ours, ref, max_fraction=1.0)


# -------------------------------------------------------------------------- properties


@given(seed=st.integers(0, 2**31 - 1))
def test_each_ray_is_traced_alone(seed):
    """Per-thread scratch slots carry nothing from one ray to the next: permuted and split batches give
    the permuted and concatenated results exactly."""
    rng = np.random.default_rng(seed)
    caster = _random_scene(rng)
    origins, dirs, tmax = _random_rays(rng, 700, caster)
    whole = caster.closest_hit(origins, dirs, tmax)
    perm = rng.permutation(len(origins))
    permuted = caster.closest_hit(origins[perm], dirs[perm], tmax[perm])
    cut = int(rng.integers(1, len(origins)))
    parts = [caster.closest_hit(origins[s], dirs[s], tmax[s]) for s in (slice(0, cut), slice(cut, None))]
    for field in ("hit", "object", "triangle", "barycentric", "distance"):
        np.testing.assert_array_equal(getattr(permuted, field), getattr(whole, field)[perm])
        np.testing.assert_array_equal(np.concatenate([getattr(p, field) for p in parts]), getattr(whole, field))
    occ = caster.occluded(origins, dirs, tmax)
    np.testing.assert_array_equal(caster.occluded(origins[perm], dirs[perm], tmax[perm]), occ[perm])


@given(seed=st.integers(0, 2**31 - 1))
def test_packets_give_the_hits_of_one_ray_calls(seed):
    """``rtcIntersect16`` / ``rtcOccluded16`` over 16 consecutive rays (the default) give the hits of
    ``rtcIntersect1`` / ``rtcOccluded1`` ray by ray, bit for bit: incoherent rays, a point's fan of
    rays (coherent), rays not cast (``tmax <= 0``) in a packet and a count not a multiple of 16."""
    from prtlab.geometry import _raycast

    rng = np.random.default_rng(seed)
    caster = _random_scene(rng)
    origins, dirs, tmax = _random_rays(rng, 333, caster)
    fan = random_directions(rng, 101)
    origins = np.concatenate([origins, np.repeat(rng.normal(size=(1, 3)), 101, axis=0)])
    dirs = np.concatenate([dirs, fan])
    tmax = np.concatenate([tmax, np.where(rng.random(101) < 0.2, 0.0, np.inf)])
    runs, default = {}, _raycast.PACKETS
    try:
        for packets in (True, False):
            _raycast.PACKETS = packets
            runs[packets] = caster.closest_hit(origins, dirs, tmax), caster.occluded(origins, dirs, tmax)
    finally:
        _raycast.PACKETS = default
    (packet, packet_occ), (single, single_occ) = runs[True], runs[False]
    for field in ("hit", "object", "triangle", "barycentric", "distance", "point", "normal"):
        np.testing.assert_array_equal(getattr(packet, field), getattr(single, field), err_msg=field)
    np.testing.assert_array_equal(packet_occ, single_occ)
    assert 0.1 < single.hit.mean() < 0.9


@given(seed=st.integers(0, 2**31 - 1))
def test_tmax_just_past_the_closest_hit_keeps_it_and_just_short_loses_it(seed):
    rng = np.random.default_rng(seed)
    caster = _random_scene(rng)
    origins, dirs, _ = _random_rays(rng, 200, caster)
    hits = caster.closest_hit(origins, dirs)
    t = hits.distance[hits.hit]
    o, d = origins[hits.hit], dirs[hits.hit]
    past = caster.closest_hit(o, d, t * (1 + 1e-6))  # 1e-6 >> a float32 ulp (6e-8) of tmax
    np.testing.assert_array_equal(past.triangle, hits.triangle[hits.hit])
    np.testing.assert_array_equal(past.distance, t)
    assert not caster.closest_hit(o, d, t * (1 - 1e-6)).hit.any()
    assert caster.occluded(o, d, t * (1 + 1e-6)).all()
    assert not caster.occluded(o, d, t * (1 - 1e-6)).any()


def test_tmax_beyond_float32_and_rays_not_cast():
    caster = RayCaster([trimesh.creation.box()])
    o = np.array([[0.0, 0.0, 5.0]] * 4)
    d = np.array([[0.0, 0.0, -1.0]] * 4)
    tmax = np.array([1e300, np.inf, 0.0, -1.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow warning from the float32 cast
        hits = caster.closest_hit(o, d, tmax)
        occ = caster.occluded(o, d, tmax)
    np.testing.assert_array_equal(hits.hit, [True, True, False, False])
    np.testing.assert_array_equal(occ, [True, True, False, False])


_THREADS_SCRIPT = textwrap.dedent("""
    import numba, numpy as np, trimesh
    from prtlab.geometry import RayCaster
    from prtlab.scene import Transform
    rng = np.random.default_rng(5)
    caster = RayCaster([trimesh.creation.icosphere(subdivisions=3), trimesh.creation.box()],
                       [None, Transform(translate=np.array([1.5, 0.0, 0.0]))])
    o = rng.normal(size=(20000, 3)) * 3.0
    d = -o + 0.8 * rng.normal(size=(20000, 3))  # most rays at the scene
    out = []
    for threads in (1, 2, 1, 2):
        numba.set_num_threads(threads)
        h = caster.closest_hit(o, d)
        out.append((h.hit, h.object, h.triangle, h.barycentric, h.distance, caster.occluded(o, d, 3.0)))
    same = all(np.array_equal(a, b) for run in out[1:] for a, b in zip(out[0], run))
    print("threads", numba.get_num_threads(), "same", same, "hits", int(out[0][0].sum()))
""")


def test_results_do_not_depend_on_the_thread_count():
    env = dict(os.environ, NUMBA_NUM_THREADS="2")
    run = subprocess.run([sys.executable, "-c", _THREADS_SCRIPT], env=env, capture_output=True, text=True,
                         timeout=600, cwd=os.path.dirname(os.path.dirname(os.path.dirname(__file__))))
    assert run.returncode == 0, run.stderr
    words = run.stdout.split()
    assert words[:4] == ["threads", "2", "same", "True"], run.stdout
    assert int(words[5]) > 5000


# ------------------------------------------------------------------ library and fallback


def test_library_is_found_beside_embreex_and_used_by_default():
    import embreex

    site = os.path.dirname(os.path.dirname(os.path.abspath(embreex.__file__)))
    candidates = _embree._candidates()
    assert candidates and candidates[0].startswith(site)  # the wheel's own copy comes first
    assert _embree.load_library()._name == candidates[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        caster = RayCaster([trimesh.creation.box()])
    assert isinstance(caster._scene, _embree.EmbreeScene)


def test_missing_library_or_symbols_are_one_line_errors():
    with pytest.raises(_embree.EmbreeUnavailable, match="no Embree 4 library found"):
        _embree.load_library([])
    with pytest.raises(_embree.EmbreeUnavailable, match=r"no usable Embree 4 library: /nonexistent/libembree4\.so"):
        _embree.load_library(["/nonexistent/libembree4.so"])
    libm = __import__("ctypes.util").util.find_library("m")
    if libm:
        with pytest.raises(_embree.EmbreeUnavailable, match="lacks rtcNewDevice"):
            _embree.load_library([libm])


def test_without_the_library_the_caster_warns_and_traces_through_embreex(monkeypatch, rng):
    mesh = trimesh.creation.icosphere(subdivisions=2)
    origins = 3.0 * random_directions(rng, 100)
    dirs = -origins + 0.5 * random_directions(rng, 100)
    expected = RayCaster([mesh]).closest_hit(origins, dirs)

    def unavailable():
        raise _embree.EmbreeUnavailable("no Embree 4 library found beside embreex or on the system path")

    monkeypatch.setattr(_embree, "load_library", unavailable)
    with pytest.warns(RuntimeWarning, match="no Embree 4 library found .*; RayCaster traces through embreex"):
        caster = RayCaster([mesh])
    assert caster._scene is None
    hits = caster.closest_hit(origins, dirs)
    np.testing.assert_array_equal(hits.triangle, expected.triangle)
    np.testing.assert_array_equal(hits.distance, expected.distance)
    np.testing.assert_array_equal(caster.occluded(origins, dirs), expected.hit)


def test_method_is_validated():
    caster = RayCaster([trimesh.creation.box()])
    with pytest.raises(ValueError, match="method must be one of 'embree', 'embreex', 'numpy', got 'optix'"):
        caster.occluded(np.zeros(3), np.ones(3), method="optix")


# ---------------------------------------------------------------------------- lifetime


def test_scenes_are_released_with_their_pose_and_their_caster():
    box = trimesh.creation.box()
    caster = RayCaster([box, box], [None, Transform(translate=np.array([3.0, 0, 0]))])
    first = caster._scene._finalizer
    caster.closest_hit([0.0, 0, 5], [0.0, 0, -1], method="embreex")  # builds the embreex scene too
    assert caster.update_transforms({1: Transform(translate=np.array([0.0, 3.0, 0]))})
    gc.collect()
    assert not first.alive  # the previous pose's Embree scene and device were released
    assert caster.closest_hit([0.0, 10, 0], [0.0, -1, 0]).object == 1
    second = caster._scene._finalizer
    del caster
    gc.collect()
    assert not second.alive


def test_release_is_idempotent():
    scene = _embree.EmbreeScene([(np.eye(3), np.array([[0, 1, 2]]))])
    assert scene.handle
    scene.release()
    scene.release()


def test_thread_benchmark_reports_its_figures(monkeypatch):
    import importlib.util
    from pathlib import Path

    import prtlab
    import prtlab.bench

    monkeypatch.setattr(prtlab.bench, "_CASES", {})  # register the cases apart from the runner's own
    path = Path(prtlab.__file__).parent / "benchmarks" / "bench_raycast.py"
    spec = importlib.util.spec_from_file_location("bench_raycast_under_test", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    case = module.threads_occluded_case(quick=True)
    case["run"]()
    case["peer"][1]()
    assert set(case["info"]) >= {"threads", "cpu_per_wall_2", "cpu_2_over_1", "rays_per_s_1", "rays_per_s_2"}
    assert case["info"]["rays_per_s_2"] > 0
