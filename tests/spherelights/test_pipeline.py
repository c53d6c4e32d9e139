"""Tests of prtlab.spherelights._pipeline (the Precomputation subclass and prtlab.shade)."""

import numpy as np
import pytest

import prtlab
from prtlab.pipeline import FrameState
from prtlab.scene import Scene, Transform
from prtlab.spherelights import SphereLights


def _scene(constant=(1.0, 0.9, 0.8), lights=None):
    return Scene.from_dict({
        "objects": [
            {"name": "plane", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [8, 8]},
             "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
            {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 2},
             "transform": {"translate": [0.3, 0.6, -0.2]},
             "material": {"type": "diffuse", "albedo": [0.8, 0.3, 0.2]}, "dynamic": True},
            {"name": "box", "mesh": {"builtin": "box", "size": [0.6, 0.6, 0.6], "subdivisions": 1},
             "transform": {"translate": [-0.9, 0.3, 0.4], "rotate_deg": [0, 30, 0]},
             "material": {"type": "diffuse", "albedo": [0.3, 0.6, 0.8]}, "dynamic": True},
        ],
        "lights": lights if lights is not None else [{"type": "environment", "constant": list(constant)}],
    })


@pytest.fixture(scope="module")
def pre():
    return SphereLights.precompute(_scene(), {"n_spheres": 2, "grid_resolution": 16}, cache=False, progress=False)


def _moved(pre, f):
    """FrameState with every object's transform composed with the similarity ``f``."""
    return FrameState(transforms={o.name: f(o.transform) for o in pre.scene.objects}, lights=list(pre.scene.lights))


def test_shade_through_the_api(tmp_path):
    res = prtlab.shade(_scene(), method="spherelights", bounces=1, cache=False, progress=False,
                       n_spheres=1, grid_resolution=16)
    for name in ("plane", "ball", "box"):
        assert res.total[name].shape == res.direct[name].shape
        assert np.all(np.isfinite(res.total[name]))
        np.testing.assert_allclose(res.total[name], res.direct[name] + res.indirect[name])
    # the spheres light the plane (positive indirect somewhere) and bounces=0 removes it
    assert res.indirect["plane"].max() > 0
    res0 = prtlab.shade(_scene(), method="spherelights", bounces=0, cache=False, progress=False,
                        n_spheres=1, grid_resolution=16)
    assert np.all(res0.indirect["plane"] == 0)
    np.testing.assert_allclose(res0.direct["plane"], res.direct["plane"])


def test_unoccluded_plane_vertex_gets_the_constant_environment(pre):
    res = pre.shade(bounces=0)
    # far corner of the plane: tiny spheres' shadow; E = pi L for a constant environment
    corner = np.argmax(np.linalg.norm(pre.scene.object("plane").world_vertices(), axis=1))
    np.testing.assert_allclose(res.direct["plane"][corner], 0.7 * np.array([1.0, 0.9, 0.8]), rtol=0.02)


@pytest.mark.parametrize("kind", ["translate", "rotate", "scale"])
def test_similarity_of_the_whole_scene_changes_nothing(pre, kind):
    """Under a constant environment, moving every object by one similarity leaves each vertex's radiance
    unchanged: lights rotate by their ``w_theta`` (Sec. 7.1), blockers move with the centres."""
    base = pre.shade(bounces=1)
    R = Transform(rotate_deg=np.array([0.0, 70.0, 0.0])).rotation
    s = 1.7

    def move(t):
        if kind == "translate":
            return Transform(translate=t.translate + [2.0, 0.0, -1.0], rotate_deg=t.rotate_deg, scale=t.scale)
        if kind == "scale":
            return Transform(translate=s * t.translate, rotate_deg=t.rotate_deg, scale=s * t.scale)
        from prtlab.scene import matrix_to_euler

        return Transform(translate=R @ t.translate, rotate_deg=matrix_to_euler(R @ t.rotation), scale=t.scale)

    moved = pre.shade(_moved(pre, move), bounces=1)
    for name in base.total:
        np.testing.assert_allclose(moved.direct[name], base.direct[name], atol=1e-8)
        np.testing.assert_allclose(moved.indirect[name], base.indirect[name], atol=1e-8)


def test_blocking_and_exp_methods_run(pre):
    for blocking in ("object", "sphere"):
        for exp_method in ("hyb", "ol", "exact"):
            p = SphereLights(pre.scene, SphereLights.make_options(
                {"n_spheres": 2, "grid_resolution": 16, "blocking": blocking, "exp_method": exp_method}), pre.data)
            res = p.shade(bounces=1)
            assert np.all(np.isfinite(res.total["plane"]))


def test_errors(pre):
    with pytest.raises(ValueError, match="at most 1 indirect bounce"):
        pre.shade(bounces=2)
    with pytest.raises(ValueError, match="exp_method must be"):
        SphereLights.make_options({"exp_method": "taylor"})
    with pytest.raises(ValueError, match="blocking must be"):
        SphereLights.make_options({"blocking": "pixel"})
    with pytest.raises(ValueError, match="order must be an int in 1..8"):
        SphereLights.make_options({"order": 9})
    scene = _scene(lights=[{"type": "point", "position": [0, 3, 0], "intensity": [1, 1, 1]}])
    p = SphereLights(scene, pre.options, pre.data)
    with pytest.raises(ValueError, match="environment lighting only"):
        p.shade(bounces=1)


def test_objects_with_different_sphere_counts():
    pre = SphereLights.precompute(_scene(), {"n_spheres": {"ball": 1, "box": 3}, "grid_resolution": 12},
                                  cache=False, progress=False)
    centres, radii, sl_object, inter, *_ = pre.world_lights(FrameState.from_scene(pre.scene))
    assert radii.shape == (4,) and inter.shape == (4, 4)
    assert not inter[:1, 1:].any()  # lights of different objects never count as intersecting
    assert np.all(np.isfinite(pre.shade(bounces=1).total["plane"]))


def test_occluding_ground_hides_the_environment_from_the_first_pass(pre):
    from prtlab.spherelights import ground_rectangles

    rect = ground_rectangles([pre.scene.object("plane")])
    np.testing.assert_allclose(rect, [[0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 2.0]], atol=1e-12)  # 4 x 4 plane at y = 0
    assert ground_rectangles([pre.scene.object("ball")]).shape == (0, 7)  # not flat: no ground
    off = SphereLights(pre.scene, SphereLights.make_options({"n_spheres": 2, "grid_resolution": 16,
                                                             "occluding_ground": False}), pre.data)
    a, b = pre.shade(bounces=1), off.shade(bounces=1)
    np.testing.assert_allclose(a.direct["plane"], b.direct["plane"])
    assert a.indirect["plane"].sum() < b.indirect["plane"].sum()
