"""The shared two-phase pipeline base: options, caching, bounce limits."""

from dataclasses import dataclass

import numpy as np
import pytest

from prtlab.cache import Cache
from prtlab.geometry import builtin_mesh
from prtlab.pipeline import FrameState, Precomputation
from prtlab.scene import Scene, SceneObject, ShadeResult


@dataclass
class ToyOptions:
    gain: float = 2.0


class Toy(Precomputation):
    method = "toy"
    max_bounces = 1
    options_type = ToyOptions
    calls = 0

    @classmethod
    def compute(cls, scene, options, progress):
        cls.calls += 1
        return {obj.name: np.full(obj.n_vertices, options.gain) for obj in scene.objects}

    def shade_frame(self, state, bounces):
        result = ShadeResult()
        for obj in self.scene.objects:
            value = np.repeat(self.data[obj.name][:, None], 3, axis=1)
            result.direct[obj.name] = value
            result.indirect[obj.name] = value * bounces
            result.total[obj.name] = value * (1 + bounces)
        return result


@pytest.fixture
def scene():
    return Scene(objects=[SceneObject("floor", builtin_mesh("plane", resolution=[2, 2]))])


def test_precompute_is_cached_and_keyed_by_options(scene, tmp_path):
    cache = Cache(tmp_path, progress=False)
    Toy.calls = 0
    a = Toy.precompute(scene, {"gain": 3.0}, cache=cache)
    b = Toy.precompute(scene, {"gain": 3.0}, cache=cache)
    c = Toy.precompute(scene, {"gain": 4.0}, cache=cache)
    assert Toy.calls == 2
    np.testing.assert_array_equal(a.data["floor"], b.data["floor"])
    assert c.shade(bounces=0).total["floor"][0, 0] == 4.0


def test_shade_with_default_state(scene):
    res = Toy.shade_scene(scene, bounces=1, cache=False)
    np.testing.assert_array_equal(res.total["floor"], 4.0)
    assert FrameState.from_scene(scene).transforms["floor"] is scene.objects[0].transform


def test_too_many_bounces_is_an_error(scene):
    pre = Toy.precompute(scene, cache=False)
    with pytest.raises(ValueError, match="method 'toy' computes at most 1 indirect bounce"):
        pre.shade(bounces=2)
    with pytest.raises(ValueError, match="bounces must be an int >= 0"):
        pre.shade(bounces=-1)


def test_unknown_option_is_an_error(scene):
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['gian'\] for method 'toy'"):
        Toy.precompute(scene, {"gian": 1.0}, cache=False)


class Baked(Toy):
    """A toy that bakes every object's pose in, takes deformations and refuses point lights."""

    method = "baked"
    supports_deformations = True
    baked_reason = "the baked toy precomputes the poses"

    def baked_objects(self):
        return tuple(o.name for o in self.scene.objects)

    @classmethod
    def check_lights(cls, lights, options):
        if lights:
            raise ValueError("the baked toy takes no lights")

    def shade_frame(self, state, bounces):
        self.seen = state
        return super().shade_frame(state, bounces)


def test_a_moved_baked_object_is_refused_and_the_same_pose_is_not(scene):
    from prtlab.scene import Transform

    pre = Baked.precompute(scene, cache=False)
    state = FrameState.from_scene(scene)
    state.transforms["floor"] = Transform(translate=np.array([0.0, 1e-6, 0.0]))
    with pytest.raises(ValueError, match=r"^the baked toy precomputes the poses: object 'floor' moved; keep it at its "
                                         r"precomputed pose \(mark it static\) or re-precompute at the new pose"):
        pre.shade(state, bounces=0)
    assert pre.moved_objects(state) == ["floor"]
    state.transforms["floor"] = Transform(translate=np.array([0.0, 1e-15, 0.0]))  # round-off is no motion
    assert pre.moved_objects(state) == []
    pre.shade(state, bounces=0)
    assert Toy.precompute(scene, cache=False).moved_objects(state) == []  # nothing baked by default


def test_the_frame_state_is_checked_before_shading(scene):
    from prtlab.scene import PointLight

    pre = Baked.precompute(scene, cache=False)
    verts = np.asarray(scene.objects[0].mesh.vertices)
    pre.shade(FrameState(deformations={"floor": verts.tolist()}), bounces=0)
    assert pre.seen.deformations["floor"].dtype == np.float64
    with pytest.raises(ValueError, match=r"deformed\['floor'\] must be finite object-space vertex positions of "
                                         r"shape \(9, 3\), got shape \(2, 3\)"):
        pre.shade(FrameState(deformations={"floor": verts[:2]}), bounces=0)
    with pytest.raises(ValueError, match=r"the frame state's deformations name unknown object\(s\) \['wall'\]"):
        pre.shade(FrameState(deformations={"wall": verts}), bounces=0)
    with pytest.raises(ValueError, match="method 'toy' does not take soft deformations"):
        Toy.precompute(scene, cache=False).shade(FrameState(deformations={"floor": verts}), bounces=0)
    with pytest.raises(ValueError, match="the baked toy takes no lights"):
        pre.shade(FrameState(lights=[PointLight(position=np.zeros(3), intensity=np.ones(3))]), bounces=0)


def test_shade_scene_checks_bounces_and_lights_before_precomputing(scene, monkeypatch):
    from prtlab.scene import PointLight

    Toy.calls = Baked.calls = 0
    with pytest.raises(ValueError, match="method 'toy' computes at most 1 indirect bounce"):
        Toy.shade_scene(scene, bounces=2, cache=False)
    lit = Scene(objects=scene.objects, lights=[PointLight(position=np.zeros(3), intensity=np.ones(3))])
    with pytest.raises(ValueError, match="the baked toy takes no lights"):
        Baked.shade_scene(lit, bounces=1, cache=False)
    assert Toy.calls == Baked.calls == 0


def test_check_scene_runs_before_compute(scene, monkeypatch):
    monkeypatch.setenv("PRTLAB_MAX_MEMORY_GB", "1")

    class Hungry(Toy):
        method = "hungry"

        @classmethod
        def memory_needs(cls, scene, options):
            from prtlab.pipeline import MemoryNeed

            return [MemoryNeed("the gains", options.gain * 2**30, ("gain",))], f"{len(scene.objects)} object"

    Hungry.calls = 0
    Hungry.precompute(scene, {"gain": 0.5}, cache=False)
    with pytest.raises(ValueError, match=r"hungry: option gain=3.0 needs ~3 GB for 1 object \(limit 1 GB"):
        Hungry.precompute(scene, {"gain": 3.0}, cache=False)
    assert Hungry.calls == 1


def test_only_resumable_methods_take_map_fn(scene):
    with pytest.raises(ValueError, match="method 'toy' cannot distribute its precomputation"):
        Toy.precompute(scene, cache=False, map_fn=map)


# ------------------------------------------------------------------ the contract, on the three pipelines

_TINY_OPTIONS = {
    "interreflection": dict(order=2, n_radii=4, resolution=4, degree=15, n_lights=16, n_basis=4, pca_occluders=False),
    "spherelights": dict(n_spheres=2, fit_resolution=12, n_directions=12, cube_resolution=4),
    "portals": dict(cube_resolution=4, direct_samples=16, n_photons=2000, gather_rays=8, order=2, bounces=1),
}


def _tiny_scene_with_a_window(method):
    """A ball on a plane under a sky with a window object (a portal) beside them; the window box for portals."""
    from tests.portals.conftest import window_box

    window = window_box(cell=1.0)
    if method == "portals":
        return window
    scene = Scene.from_dict({
        "objects": [
            {"name": "plane", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [3, 3]},
             "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
            {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 1},
             "transform": {"translate": [0.0, 0.5, 0.0]}, "material": {"type": "diffuse", "albedo": [0.8, 0.3, 0.2]}},
        ],
        "lights": [{"type": "environment", "sky": {"sun_elevation_deg": 30, "height": 16, "width": 32}}],
    })
    scene.objects.append(window.object("window"))
    return scene


@pytest.mark.parametrize("method", ["interreflection", "spherelights", "portals"])
def test_every_pipeline_returns_the_shaded_objects_and_the_common_info_keys(method):
    import prtlab

    scene = _tiny_scene_with_a_window(method)
    result = prtlab.shade(scene, method=method, cache=False, progress=False, **_TINY_OPTIONS[method])
    shaded = sorted(o.name for o in scene.objects if not o.portal)
    assert sorted(result.total) == sorted(result.direct) == sorted(result.indirect) == shaded
    assert "window" not in result.total
    assert result.info["method"] == method and result.info["bounces"] == 1
    timings = result.info["timings"]
    assert isinstance(timings, dict) and timings
    assert all(isinstance(t, float) and t >= 0 for t in timings.values())


@pytest.mark.parametrize("method", ["interreflection", "spherelights", "portals"])
def test_every_entry_point_defaults_to_one_bounce(method):
    import inspect

    import prtlab
    from prtlab.api import pipeline_class

    module = __import__(f"prtlab.{method}", fromlist=["shade_scene"])
    for function in (module.shade_scene, pipeline_class(method).shade_scene, pipeline_class(method).shade,
                     prtlab.shade):
        assert inspect.signature(function).parameters["bounces"].default == 1, function


@pytest.mark.parametrize("method, old, new", [("portals", "res", "cube_resolution"),
                                              ("interreflection", "haar_resolution", "cube_resolution"),
                                              ("spherelights", "grid_resolution", "fit_resolution")])
def test_a_renamed_option_names_its_new_name(method, old, new):
    from prtlab.api import pipeline_class

    with pytest.raises(ValueError, match=rf"option '{old}' of method '{method}' is now called '{new}'; "
                                         rf"pass {new}=\.\.\. instead"):
        pipeline_class(method).make_options({old: 8})
