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
