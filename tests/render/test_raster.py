"""Rasterising per-vertex radiance: exact interpolation, background, lights; figure helpers."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest

from prtlab.geometry import builtin_mesh, equirect_lookup
from prtlab.render import (
    agreement_plot,
    barycentric_coordinates,
    camera_rays,
    comparison_figure,
    difference_figure,
    render_image,
)
from prtlab.scene import AreaLight, Camera, EnvironmentLight, Material, Scene, SceneObject, ShadeResult, Transform


def _scene(lights=(), resolution=(24, 18)):
    floor = SceneObject("floor", builtin_mesh("plane", size=[4, 4], resolution=[5, 3]),
                        Transform(np.array([0.1, -0.2, 0.3]), np.array([10.0, 25.0, -5.0])), Material())
    cam = Camera(position=np.array([0.5, 3.0, 4.0]), look_at=np.zeros(3), fov_deg=45.0, resolution=resolution)
    return Scene(objects=[floor], lights=list(lights), camera=cam)


def _linear_result(scene, a, b):
    obj = scene.objects[0]
    values = obj.world_vertices() @ a.T + b
    return ShadeResult(direct={obj.name: values}, indirect={obj.name: 0 * values}, total={obj.name: values})


def test_linear_vertex_function_is_reproduced_exactly_at_pixel_centres():
    scene = _scene()
    a = np.array([[1.0, 2.0, -0.5], [0.3, -1.0, 0.7], [-2.0, 0.1, 0.4]])
    b = np.array([3.0, 4.0, 5.0])
    img = render_image(scene, _linear_result(scene, a, b), background=False)
    origins, dirs = camera_rays(scene.camera)
    obj = scene.objects[0]
    verts = obj.world_vertices()
    n = obj.transform.rotation @ np.array([0.0, 1.0, 0.0])
    t = ((verts[0] - origins) @ n) / (dirs @ n)
    hit_points = origins + t[..., None] * dirs
    local = (hit_points - obj.transform.translate) @ obj.transform.rotation  # back to object space
    inside = (np.abs(local[..., 0]) < 2 - 1e-6) & (np.abs(local[..., 2]) < 2 - 1e-6) & (t > 0)
    outside = (np.abs(local[..., 0]) > 2 + 1e-6) | (np.abs(local[..., 2]) > 2 + 1e-6) | (t < 0)
    assert inside.sum() > 100 and outside.sum() > 10
    expect = hit_points @ a.T + b
    np.testing.assert_allclose(img[inside], expect[inside], rtol=1e-10, atol=1e-10)
    np.testing.assert_array_equal(img[outside], 0.0)


def test_barycentric_coordinates_reproduce_the_hit_point(rng):
    a, b, c = rng.normal(size=(3, 20, 3))
    w = rng.dirichlet([1, 1, 1], size=20)
    target = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
    origins = target + rng.normal(size=(20, 3))
    bary, t = barycentric_coordinates(origins, target - origins, a, b, c)
    np.testing.assert_allclose(bary, w, atol=1e-10)
    np.testing.assert_allclose(t, 1.0, atol=1e-10)


def test_background_is_the_environment_in_the_ray_direction(rng):
    image = rng.uniform(0, 3, size=(9, 16, 3))
    scene = _scene([EnvironmentLight(image=image)])
    scene.camera = Camera(position=np.array([0, 1.0, 6.0]), look_at=np.array([0, 3.0, 0]), resolution=(12, 8))
    img = render_image(scene, _linear_result(scene, np.eye(3), np.zeros(3)))
    _, dirs = camera_rays(scene.camera)
    np.testing.assert_allclose(img[0], equirect_lookup(image, dirs[0]), rtol=1e-12)


def test_area_light_seen_from_the_front_and_from_behind():
    # between the camera and the floor, facing the camera: its radiance; turned away: black
    facing = AreaLight(np.array([0.0, 1.5, 2.0]), np.array([0.3, 0, 0]), np.array([0, 0.3, 0]), np.array([5.0, 6, 7]))
    scene = _scene([facing, EnvironmentLight(constant=np.ones(3))])
    scene.camera = Camera(position=np.array([0, 1.5, 5.0]), look_at=np.array([0, 1.5, 0]), resolution=(9, 9))
    res = _linear_result(scene, np.zeros((3, 3)), np.full(3, 0.25))
    img = render_image(scene, res)
    np.testing.assert_array_equal(img[4, 4], [5.0, 6.0, 7.0])
    scene.lights[0] = AreaLight(facing.center, facing.v, facing.u, facing.radiance)
    np.testing.assert_array_equal(render_image(scene, res)[4, 4], 0.0)


def test_parts_select_the_result_field():
    scene = _scene()
    res = _linear_result(scene, np.zeros((3, 3)), np.ones(3))
    assert render_image(scene, res, part="indirect").max() == 0.0
    assert render_image(scene, res, part="direct").max() == 1.0


def test_render_errors():
    scene = _scene()
    res = _linear_result(scene, np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="part must be one of"):
        render_image(scene, res, part="glossy")
    with pytest.raises(TypeError, match="result must be a prtlab.ShadeResult"):
        render_image(scene, {"floor": 1})
    with pytest.raises(TypeError, match="scene must be a prtlab.Scene"):
        render_image(None, res)
    with pytest.raises(KeyError, match="no 'total' radiance for object 'floor'"):
        render_image(scene, ShadeResult())
    bad = ShadeResult(total={"floor": np.zeros((3, 3))})
    with pytest.raises(ValueError, match=r"result.total\['floor'\] must have shape"):
        render_image(scene, bad)


# --------------------------------------------------------------------------- figure helpers


def test_figure_helpers(rng):
    a = rng.uniform(0, 1, size=(6, 8, 3))
    b = a * 1.1
    fig = comparison_figure([a, b], ["own", "mitsuba"])
    assert len(fig.axes) == 2
    fig = difference_figure(a, b, mode="relative")
    assert len(fig.axes) == 2  # image and colour bar
    difference_figure(a, b, mode="signed")
    x = rng.uniform(0, 1, size=(40, 3))
    fig = agreement_plot(x, x + 0.01, 0.01 * np.ones_like(x), 0.02 * np.ones_like(x))
    assert fig.axes[0].get_xlabel() == "reference"
    import matplotlib.pyplot as plt

    plt.close("all")


def test_figure_errors(rng):
    a = rng.uniform(0, 1, size=(6, 8, 3))
    with pytest.raises(ValueError, match="images is empty"):
        comparison_figure([])
    with pytest.raises(ValueError, match="titles has 1 entries for 2 images"):
        comparison_figure([a, a], ["x"])
    with pytest.raises(ValueError, match=r"images\[0\] must be \(h, w, 3\)"):
        comparison_figure([a[..., 0]])
    with pytest.raises(ValueError, match="mode must be"):
        difference_figure(a, a, mode="ratio")
    with pytest.raises(ValueError, match="same shape"):
        difference_figure(a, a[:3])
    with pytest.raises(ValueError, match="reference and estimate must have the same shape"):
        agreement_plot(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match="estimate_err must have the shape"):
        agreement_plot(np.zeros(3), np.zeros(3), None, np.zeros(4))
    with pytest.raises(ValueError, match="channel must be"):
        agreement_plot(np.zeros((3, 3)), np.zeros((3, 3)), channel="alpha")
    from prtlab.render import luminance

    with pytest.raises(ValueError, match=r"img must be a \(\.\.\., 3\) RGB array"):
        luminance(np.zeros((4, 2)))
    import matplotlib.pyplot as plt

    plt.close("all")
