"""The pipelines refuse what they cannot do before any heavy work, and never answer silently wrong.

Moved objects (baked in by portals, handled by spherelights and interreflection), late refusals
(bounces, lights, scenes), memory estimates, portal winding and negative radiance.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
import trimesh

import prtlab
from prtlab.cache import Cache, cache_key
from prtlab.interreflection import Interreflection
from prtlab.pipeline import FrameState, memory_limit
from prtlab.portals import Portals, find_portals
from prtlab.scene import Scene, Transform
from prtlab.spherelights import SphereLights
from tests.portals.conftest import window_box

#: the smallest portals options that still trace every pass
TINY_PORTALS = {"cube_resolution": 4, "direct_samples": 16, "n_photons": 2000, "gather_rays": 8, "order": 2, "bounces": 1}
TINY_SPHERES = {"n_spheres": 2, "fit_resolution": 12}
TINY_INTERREFLECTION = dict(order=2, n_radii=4, resolution=4, degree=15, n_lights=16, n_basis=4, pca_occluders=False)

#: a box that blocks the window of :func:`window_box` (wall z = -1.5, window centre x = 0, y = 1.4)
BLOCKING = Transform(translate=np.array([0.0, 1.4, -1.2]))
ASIDE = Transform(translate=np.array([1.0, 0.3, 1.0]))


def _room_with_box(transform: Transform) -> Scene:
    scene = window_box(cell=1.0)
    box = Scene.from_dict({"objects": [{"name": "box", "mesh": {"builtin": "box", "size": [1.4, 1.4, 0.3]},
                                        "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]},
                                        "dynamic": True}]}).objects[0]
    box.transform = transform
    scene.objects.append(box)
    return scene


def _spheres_scene(plane_resolution=8) -> Scene:
    return Scene.from_dict({
        "objects": [
            {"name": "plane", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [plane_resolution] * 2},
             "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
            {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 2},
             "transform": {"translate": [0.3, 0.5, -0.2]}, "dynamic": True,
             "material": {"type": "diffuse", "albedo": [0.8, 0.3, 0.2]}},
            {"name": "box", "mesh": {"builtin": "box", "size": [0.6, 0.6, 0.6]},
             "transform": {"translate": [-0.9, 0.3, 0.4]},
             "material": {"type": "diffuse", "albedo": [0.3, 0.6, 0.8]}},
        ],
        "lights": [{"type": "environment", "sky": {"sun_elevation_deg": 30, "sun_azimuth_deg": 40, "turbidity": 3,
                                                   "height": 32, "width": 64}}],
    })


@pytest.fixture
def no_compute(monkeypatch):
    """Make ``compute`` of every pipeline fail the test: a refusal must come before it."""
    def fail(*args, **kwargs):
        pytest.fail("the precomputation ran before the refusal")

    for cls in (Portals, SphereLights, Interreflection):
        monkeypatch.setattr(cls, "compute", classmethod(fail))


@pytest.fixture(scope="module")
def portals_aside():
    return Portals.precompute(_room_with_box(ASIDE), TINY_PORTALS, cache=False, progress=False)


# ------------------------------------------------------------------ moved objects (issue 13.1)


def test_the_portals_cache_key_holds_the_transforms_of_dynamic_objects():
    opts = Portals.make_options(TINY_PORTALS)
    a = cache_key(*Portals.cache_key_parts(_room_with_box(ASIDE), opts))
    b = cache_key(*Portals.cache_key_parts(_room_with_box(BLOCKING), opts))
    assert a != b


def test_a_cached_portals_precomputation_at_a_new_pose_is_the_precomputation_at_that_pose(tmp_path, portals_aside):
    cache = Cache(tmp_path, progress=False)
    Portals.precompute(_room_with_box(ASIDE), TINY_PORTALS, cache=cache, progress=False)
    cached = Portals.precompute(_room_with_box(BLOCKING), TINY_PORTALS, cache=cache, progress=False)
    fresh = Portals.precompute(_room_with_box(BLOCKING), TINY_PORTALS, cache=False, progress=False)
    blocked, fresh_total = cached.shade(bounces=1).total["room"], fresh.shade(bounces=1).total["room"]
    np.testing.assert_allclose(blocked, fresh_total, rtol=1e-6, atol=1e-12)
    # the box in front of the window darkens the room: the old entry (box aside) was not reused
    assert blocked.mean() < portals_aside.shade(bounces=1).total["room"].mean()


def test_portals_refuse_a_moved_object(portals_aside):
    state = FrameState.from_scene(portals_aside.scene)
    state.transforms["box"] = BLOCKING
    with pytest.raises(ValueError, match="the portals method precomputes the interior: object 'box' moved; "
                                         "keep it at its precomputed pose"):
        portals_aside.shade(state, bounces=1)
    assert portals_aside.moved_objects(state) == ["box"]
    # the same pose as a new Transform is no motion
    state.transforms["box"] = Transform(translate=ASIDE.translate.copy())
    assert portals_aside.moved_objects(state) == []
    assert np.all(np.isfinite(portals_aside.shade(state, bounces=1).total["room"]))


@pytest.mark.parametrize("moved", ["ball", "box"])  # a dynamic and a static object
def test_spherelights_shade_a_moved_object_as_a_precomputation_at_the_new_pose(moved):
    scene = _spheres_scene()
    pre = SphereLights.precompute(scene, TINY_SPHERES, cache=False, progress=False)
    pose = Transform(translate=np.array([0.9, 0.6, 0.8]), rotate_deg=np.array([0.0, 35.0, 10.0]), scale=1.2)
    state = FrameState.from_scene(scene)
    state.transforms[moved] = pose
    shaded = pre.shade(state, bounces=1)
    there = _spheres_scene()
    there.object(moved).transform = pose
    truth = SphereLights.precompute(there, TINY_SPHERES, cache=False, progress=False).shade(bounces=1)
    for name in truth.total:
        np.testing.assert_allclose(shaded.direct[name], truth.direct[name], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(shaded.indirect[name], truth.indirect[name], rtol=1e-9, atol=1e-12)


def test_interreflection_shades_a_moved_object_as_a_precomputation_at_the_new_pose():
    from tests.interreflection.test_pipeline import scene as ball_scene

    pre = Interreflection.precompute(ball_scene(), TINY_INTERREFLECTION, cache=False, progress=False)
    pose = Transform(translate=np.array([0.4, 0.8, -0.2]), rotate_deg=np.array([0.0, 40.0, 0.0]))
    state = FrameState.from_scene(pre.scene)
    state.transforms["ball"] = pose
    shaded = pre.shade(state, bounces=2)
    there = ball_scene()
    there.object("ball").transform = pose
    truth = Interreflection.precompute(there, TINY_INTERREFLECTION, cache=False, progress=False).shade(bounces=2)
    for name in truth.total:
        np.testing.assert_allclose(shaded.total[name], truth.total[name], rtol=1e-9, atol=1e-12)


def test_deformations_are_refused_by_the_methods_that_do_not_take_them(portals_aside):
    state = FrameState.from_scene(portals_aside.scene)
    box = portals_aside.scene.object("box")
    state.deformations = {"box": np.asarray(box.mesh.vertices) * 1.1}
    with pytest.raises(ValueError, match=r"method 'portals' does not take soft deformations .*\['box'\]"):
        portals_aside.shade(state, bounces=1)


def test_a_frame_state_naming_an_unknown_object_is_refused(portals_aside):
    state = FrameState.from_scene(portals_aside.scene)
    state.transforms["teapot"] = Transform()
    with pytest.raises(ValueError, match=r"the frame state's transforms name unknown object\(s\) \['teapot'\]"):
        portals_aside.shade(state, bounces=1)


def test_spherelights_take_deformations_through_the_frame_state():
    scene = _spheres_scene(plane_resolution=4)
    pre = SphereLights.precompute(scene, TINY_SPHERES, cache=False, progress=False)
    t = np.array([0.3, 0.0, 0.2])
    ball = scene.object("ball")
    by_keyword = pre.shade(bounces=1, deformed={"ball": np.asarray(ball.mesh.vertices) + t})
    state = FrameState.from_scene(scene)
    state.deformations = {"ball": np.asarray(ball.mesh.vertices) + t}
    by_state = pre.shade(state, bounces=1)
    for name in by_state.total:
        np.testing.assert_array_equal(by_state.total[name], by_keyword.total[name])
    assert not hasattr(pre, "_deformed")


# ------------------------------------------------------------------ refusals before any work (issue 13.9)


def test_spherelights_refuse_three_bounces_before_precomputing(no_compute):
    with pytest.raises(ValueError, match="method 'spherelights' computes at most 2 indirect bounce"):
        prtlab.shade(_spheres_scene(), method="spherelights", bounces=3, cache=False, progress=False)


def test_portals_refuse_more_bounces_than_the_option_before_precomputing(no_compute):
    with pytest.raises(ValueError, match="precomputed with bounces=1; shade with bounces <= 1"):
        Portals.shade_once(window_box(cell=1.0), TINY_PORTALS, bounces=2, cache=False, progress=False)


@pytest.mark.parametrize("method, options, light, message", [
    ("spherelights", {}, {"type": "point", "position": [0, 3, 0], "intensity": [1, 1, 1]},
     "environment lighting only"),
    ("interreflection", {"shadows": "sh"}, {"type": "point", "position": [0, 3, 0], "intensity": [1, 1, 1]},
     "not point lights; pass shadows='rays' or 'haar'"),
    ("portals", {}, {"type": "area", "center": [0, 2.4, 0], "u": [0.2, 0, 0], "v": [0, 0, 0.2],
                     "radiance": [1, 1, 1]}, "exactly one environment light"),
])
def test_unsupported_lights_are_refused_before_precomputing(no_compute, method, options, light, message):
    scene = window_box(cell=1.0) if method == "portals" else _spheres_scene()
    plane = {"name": "plane", "mesh": {"builtin": "plane", "size": [1, 1], "resolution": [1, 1]}}
    scene.lights = Scene.from_dict({"objects": [plane], "lights": [light]}).lights
    with pytest.raises(ValueError, match=message):
        prtlab.shade(scene, method=method, bounces=1, cache=False, progress=False, **options)


def test_portals_refuse_a_scene_without_portal_before_precomputing(no_compute):
    scene = _spheres_scene()
    with pytest.raises(ValueError, match="the scene has no portal: mark the window objects with 'portal: true'"):
        prtlab.precompute(scene, "portals", progress=False)


def _with_vertex_without_normal(scene: Scene, name: str, kind: str) -> Scene:
    """``scene`` with one vertex appended to object ``name``'s mesh: unreferenced, or the corner of one
    zero-area face (its only face), so that its vertex normal is zero."""
    obj = scene.object(name)
    v, f = np.asarray(obj.mesh.vertices), np.asarray(obj.mesh.faces)
    v = np.vstack([v, v.mean(axis=0)])
    if kind == "degenerate":  # a sliver: the new vertex and a face's edge, all on one line
        a, b = v[f[0, 0]], v[f[0, 1]]
        v[-1] = 0.5 * (a + b)
        f = np.vstack([f, [f[0, 0], f[0, 1], len(v) - 1]])
    obj.mesh = trimesh.Trimesh(v, f, process=False)
    assert not np.any(obj.mesh.vertex_normals[-1])
    return scene


@pytest.mark.parametrize("kind", ["unreferenced", "degenerate"])
@pytest.mark.parametrize("method", ["interreflection", "spherelights", "portals"])
def test_a_vertex_without_a_normal_is_refused_before_precomputing(no_compute, method, kind):
    """Every PRT method shades a vertex about its normal; one without a normal stopped the frame, after the
    precomputation (e.g. ``normals contains a zero vector``, a singular matrix)."""
    scene, name = (window_box(cell=1.0), "room") if method == "portals" else (_spheres_scene(), "box")
    n = scene.object(name).n_vertices
    with pytest.raises(ValueError, match=rf"object '{name}': 1 of its {n + 1} vertices has no normal \(vertex {n}: "):
        prtlab.shade(_with_vertex_without_normal(scene, name, kind), method=method, cache=False, progress=False)


def test_the_reference_gives_a_vertex_without_a_normal_no_light():
    scene = _with_vertex_without_normal(_spheres_scene(plane_resolution=2), "box", "unreferenced")
    result = prtlab.shade(scene, method="reference", n_samples=16)
    assert np.all(result.total["box"][-1] == 0.0) and np.all(result.total["box"][:-1].max(axis=1) > 0.0)


@pytest.mark.parametrize("method", list(prtlab.api.METHODS))
@pytest.mark.parametrize("bounces, error", [(-1, ValueError), (1.5, TypeError), (True, TypeError),
                                            (np.float64(1.0), TypeError)])
def test_bad_bounces_are_refused_by_every_method(no_compute, method, bounces, error):
    with pytest.raises(error, match="bounces must be an int >= 0"):
        prtlab.shade(_spheres_scene(), method=method, bounces=bounces, progress=False)


# ------------------------------------------------------------------ memory (issue 13.10)


def _fast(fn):
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


@pytest.mark.parametrize("method, options, named", [
    ("portals", dict(TINY_PORTALS, order=8, cube_resolution=64, bounces=40, n_photons=2_000_000, gather_rays=4096,
                     indirect="paper"),
     r"portals: option (order|gather_rays|n_photons)=\d+ with .* needs ~[\d.,]+ GB for [\d,]+ vertices"),
    ("portals", dict(TINY_PORTALS, bounces=10**6, indirect="paper"), r"portals: option .*bounces=1000000"),
    ("portals", dict(TINY_PORTALS, gather_rays=10**9, indirect="surface"), r"portals: option gather_rays=1000000000 "),
    ("portals", dict(TINY_PORTALS, cube_resolution=2**16), r"portals: option cube_resolution=65536 .*needs ~[\d.,]+ GB"),
    ("spherelights", dict(TINY_SPHERES, fit_resolution=100_000), r"spherelights: option fit_resolution=100000 "),
    ("spherelights", dict(TINY_SPHERES, cube_resolution=100_000), r"spherelights: option cube_resolution=100000 "),
    ("interreflection", dict(TINY_INTERREFLECTION, resolution=4096), r"interreflection: option .*resolution=4096"),
    ("interreflection", dict(TINY_INTERREFLECTION, n_lights=10**9), r"interreflection: option n_lights=1000000000 "),
])
def test_huge_options_are_refused_at_once_naming_the_option(monkeypatch, no_compute, method, options, named):
    monkeypatch.setenv("PRTLAB_MAX_MEMORY_GB", "1")
    scene = window_box(cell=1.0) if method == "portals" else _spheres_scene(plane_resolution=4)

    def run():
        with pytest.raises(ValueError, match=named + r".*\(limit 1 GB; mostly the .*\): lower "):
            prtlab.precompute(scene, method, progress=False, **options)

    assert _fast(run) < 1.0


def test_the_reference_refuses_a_wavefront_beyond_memory(monkeypatch):
    monkeypatch.setenv("PRTLAB_MAX_MEMORY_GB", "1")
    with pytest.raises(ValueError, match=r"reference: option n_samples=1000000000 needs ~[\d.,]+ GB for [\d,]+ points "
                                         r"\(limit 1 GB; mostly the path wavefront\): lower n_samples"):
        prtlab.shade(window_box(cell=1.5), method="reference", bounces=1, n_samples=10**9, progress=False)


def test_the_memory_limit_reads_the_environment(monkeypatch):
    monkeypatch.setenv("PRTLAB_MAX_MEMORY_GB", "2.5")
    assert memory_limit() == 2.5 * 2**30
    monkeypatch.setenv("PRTLAB_MAX_MEMORY_GB", "lots")
    with pytest.raises(ValueError, match="environment variable PRTLAB_MAX_MEMORY_GB must be a number of GB > 0, "
                                         "got 'lots'"):
        memory_limit()
    monkeypatch.delenv("PRTLAB_MAX_MEMORY_GB")
    assert memory_limit() is None or memory_limit() > 0


def test_default_options_fit_on_a_small_scene(monkeypatch):
    monkeypatch.setenv("PRTLAB_MAX_MEMORY_GB", "2")
    scene = window_box()
    for cls in (Portals, SphereLights, Interreflection):
        cls.check_scene(scene if cls is Portals else _spheres_scene(), cls.make_options(None))


# ------------------------------------------------------------------ portal winding (issue 13.11)


def _flipped_window(scene: Scene) -> Scene:
    window = scene.object("window")
    flipped = dataclasses.replace(window, mesh=trimesh.Trimesh(np.asarray(window.mesh.vertices),
                                                               np.asarray(window.mesh.faces)[:, ::-1], process=False))
    return dataclasses.replace(scene, objects=[flipped if o is window else o for o in scene.objects])


def test_a_portal_of_either_winding_faces_the_room():
    scene = window_box(cell=1.0)
    flipped = _flipped_window(scene)
    assert np.allclose(find_portals(scene)[0].normal, [0, 0, 1]) and np.allclose(find_portals(flipped)[0].normal,
                                                                                  [0, 0, 1])
    a = Portals.precompute(scene, TINY_PORTALS, cache=False, progress=False).shade(bounces=1)
    b = Portals.precompute(flipped, TINY_PORTALS, cache=False, progress=False).shade(bounces=1)
    assert a.total["room"].mean() > 0
    np.testing.assert_allclose(b.total["room"], a.total["room"], rtol=1e-9, atol=1e-12)


# ------------------------------------------------------------------ negative radiance (issue 13.11)


def test_spherelights_give_no_negative_radiance_beside_spheres_on_a_plane():
    scene = prtlab.load_scene(prtlab.api.Path(prtlab.__file__).parents[1] / "data/scenes/spheres_on_plane_env.yaml")
    scene.objects = scene.objects[:2]  # the plane and the red sphere
    res = SphereLights.precompute(scene, {"n_spheres": 1, "fit_resolution": 12}, cache=False,
                                  progress=False).shade(bounces=1)
    for part in ("direct", "indirect", "total"):
        for name, value in getattr(res, part).items():
            assert value.min() >= 0.0, (part, name, value.min())
    assert res.direct["plane"].max() > 0


def test_spherelights_refuse_n_spheres_for_an_unknown_object_before_precomputing(no_compute):
    with pytest.raises(ValueError, match=r"option n_spheres names unknown object\(s\) \['teapot'\]; objects: "):
        prtlab.shade(_spheres_scene(), method="spherelights", cache=False, progress=False, n_spheres={"teapot": 2})


def test_portals_stream_the_photon_estimates_and_gathering_in_smaller_chunks_with_the_same_result(monkeypatch):
    import prtlab.portals._indirect as indirect

    scene = window_box(cell=1.0)
    options = dict(TINY_PORTALS, bounces=2, order=3, indirect="paper")
    whole = Portals.precompute(scene, options, cache=False, progress=False)
    monkeypatch.setattr(indirect, "CHUNK_BYTES", 1)  # one vertex per chunk
    streamed = Portals.precompute(scene, options, cache=False, progress=False)
    for b in (1, 2):
        np.testing.assert_allclose(streamed.indirect_transfer(0, b), whole.indirect_transfer(0, b), rtol=1e-6,
                                   atol=1e-12)


def test_mitsuba_refuses_a_wavefront_beyond_memory_before_loading_mitsuba(monkeypatch):
    monkeypatch.setenv("PRTLAB_MAX_MEMORY_GB", "1")
    with pytest.raises(ValueError, match=r"mitsuba: option n_samples=1000000000 needs ~[\d.,]+ GB for [\d,]+ vertices "
                                         r"\(limit 1 GB; mostly the ray wavefront\): lower n_samples"):
        prtlab.shade(window_box(cell=1.5), method="mitsuba", bounces=1, n_samples=10**9, progress=False)


def test_spherelights_shade_the_same_objects_as_the_other_pipelines():
    scene = _spheres_scene(plane_resolution=4)
    window = window_box(cell=1.0).object("window")
    scene.objects.append(window)
    res = SphereLights.precompute(scene, TINY_SPHERES, cache=False, progress=False).shade(bounces=1)
    assert sorted(res.total) == ["ball", "box", "plane"] and res.info["bounces"] == 1
