"""Shading points: vertices are shaded a hair inside their own faces, never in another surface."""

import numpy as np
import pytest

from prtlab.geometry import builtin_mesh, shading_points
from prtlab.reference import shade_reference
from prtlab.scene import Camera, EnvironmentLight, Material, Scene, SceneObject


def test_interior_vertices_do_not_move():
    plane = builtin_mesh("plane", size=[2, 2], resolution=[4, 4])
    points = shading_points(plane.vertices, plane.faces, plane.vertex_normals)
    interior = np.all(np.abs(plane.vertices[:, [0, 2]]) < 0.99, axis=1)
    np.testing.assert_allclose(points[interior], plane.vertices[interior], atol=1e-15)


def test_boundary_vertices_move_inward_in_the_tangent_plane():
    plane = builtin_mesh("plane", size=[2, 2], resolution=[4, 4])
    points = shading_points(plane.vertices, plane.faces, plane.vertex_normals)
    assert np.all(points[:, 1] == 0.0)  # stays in the plane
    assert np.all(np.abs(points[:, [0, 2]]) < 1.0)  # strictly inside the square
    corner = np.argmin(plane.vertices[:, 0] + plane.vertices[:, 2])
    assert np.all(points[corner, [0, 2]] > -1.0) and np.linalg.norm(points[corner] - plane.vertices[corner]) < 0.01


def test_closed_mesh_vertices_stay_on_the_tangent_plane(rng):
    sphere = builtin_mesh("icosphere", subdivisions=2)
    n = sphere.vertex_normals
    points = shading_points(sphere.vertices, sphere.faces, n)
    np.testing.assert_allclose(np.sum((points - sphere.vertices) * n, axis=1), 0.0, atol=1e-15)


def test_errors():
    with pytest.raises(ValueError, match=r"vertices and normals must both be \(V, 3\) arrays"):
        shading_points(np.zeros((3, 2)), np.zeros((1, 3), int), np.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"faces must be an \(F, 3\) integer array"):
        shading_points(np.zeros((3, 3)), np.zeros(3, int), np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"fraction must be in \[0, 1/3\)"):
        shading_points(np.zeros((3, 3)), np.zeros((1, 3), int), np.zeros((3, 3)), fraction=0.5)


def test_closed_room_does_not_leak_light_at_its_corners():
    # A closed room under a bright sky: every vertex inside, corners included, must be exactly dark.
    room = SceneObject("room", builtin_mesh("room", size=[4, 3, 4], windows=[]), material=Material(albedo=np.full(3, 0.8)))
    scene = Scene(objects=[room], lights=[EnvironmentLight(constant=np.full(3, 10.0))],
                  camera=Camera(position=np.array([0.0, 1.5, 1.0]), look_at=np.array([0.0, 1.0, -1.0])))
    result = shade_reference(scene, bounces=1, n_samples=64, seed=3, progress=False)
    assert np.max(result.total["room"]) == 0.0


def test_world_shading_points_commute_with_the_object_transform():
    from prtlab.scene import Transform

    mesh = builtin_mesh("box", subdivisions=1)
    obj = SceneObject("box", mesh, transform=Transform(np.array([1.0, 2.0, -0.5]), np.array([10.0, 35.0, -70.0]), 1.7))
    world = shading_points(obj.world_vertices(), mesh.faces, obj.world_normals())
    np.testing.assert_allclose(obj.world_shading_points(), world, atol=1e-12)
