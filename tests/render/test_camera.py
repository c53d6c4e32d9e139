"""Camera rays: the view axis, the field of view, projection round trips, errors."""

from __future__ import annotations

import numpy as np
import pytest

from prtlab.render import camera_frame, camera_rays, pixel_directions, project_points
from prtlab.scene import Camera
from tests.conftest import FLOAT_TOLERANCE

TOL = FLOAT_TOLERANCE[np.float64]


def _camera(**kw):
    base = dict(position=np.array([1.0, 2.0, 5.0]), look_at=np.array([0.0, 0.5, 0.0]), up=np.array([0.0, 1.0, 0.0]),
                fov_deg=40.0, resolution=(9, 7))
    base.update(kw)
    return Camera(**base)


def _angle(a, b):
    return np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0))


def test_centre_pixel_looks_along_the_view_axis():
    cam = _camera()  # odd width and height: the centre pixel's centre is the image centre
    origins, dirs = camera_rays(cam)
    axis = (cam.look_at - cam.position) / np.linalg.norm(cam.look_at - cam.position)
    np.testing.assert_allclose(dirs[3, 4], axis, atol=TOL)
    np.testing.assert_allclose(origins, np.broadcast_to(cam.position, origins.shape))
    assert dirs.shape == (7, 9, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=TOL)


def test_vertical_field_of_view_at_the_top_and_bottom_edges():
    cam = _camera(fov_deg=52.0, resolution=(16, 10))
    frame = camera_frame(cam)
    top = pixel_directions(cam, 8.0, 0.0)
    bottom = pixel_directions(cam, 8.0, 10.0)
    assert np.isclose(np.degrees(_angle(top, frame[2])), 26.0, atol=1e-9)
    assert np.isclose(np.degrees(_angle(top, bottom)), 52.0, atol=1e-9)
    assert top @ frame[1] > 0 > bottom @ frame[1]  # row 0 is the top


def test_horizontal_extent_follows_the_aspect_ratio():
    cam = _camera(fov_deg=40.0, resolution=(20, 10))
    frame = camera_frame(cam)
    right = pixel_directions(cam, 20.0, 5.0)
    expect = np.arctan(2.0 * np.tan(np.radians(20.0)))
    assert np.isclose(_angle(right, frame[2]), expect, atol=1e-12)
    assert right @ frame[0] > 0  # x grows to the right


def test_frame_is_right_handed_orthonormal():
    frame = camera_frame(_camera())
    np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=TOL)
    np.testing.assert_allclose(np.cross(frame[0], frame[1]), -frame[2], atol=TOL)  # right x up = backward


def test_projection_inverts_pixel_directions(rng):
    cam = _camera()
    xy = rng.uniform([0, 0], [9, 7], size=(50, 2))
    points = cam.position + 3.7 * pixel_directions(cam, xy[:, 0], xy[:, 1])
    back, depth = project_points(cam, points)
    np.testing.assert_allclose(back, xy, atol=1e-9)
    assert np.all(depth > 0)
    behind, depth = project_points(cam, 2 * cam.position - cam.look_at)
    assert np.all(np.isnan(behind)) and depth < 0


def test_camera_errors():
    with pytest.raises(TypeError, match="camera must be a prtlab.scene.Camera"):
        camera_rays({"fov_deg": 40})
    with pytest.raises(ValueError, match="fov_deg must be in"):
        camera_rays(_camera(fov_deg=180.0))
    with pytest.raises(ValueError, match="resolution must be positive"):
        camera_rays(_camera(resolution=(0, 4)))
    with pytest.raises(ValueError, match="resolution must be"):
        camera_rays(_camera(resolution=5))
    with pytest.raises(ValueError, match="look_at equals camera.position"):
        camera_rays(_camera(look_at=np.array([1.0, 2.0, 5.0])))
    with pytest.raises(ValueError, match="up is parallel"):
        camera_rays(_camera(position=np.array([0.0, 5.0, 0.0]), look_at=np.zeros(3)))
    with pytest.raises(ValueError, match="must be finite"):
        camera_rays(_camera(position=np.array([np.nan, 0, 0])))
    with pytest.raises(ValueError, match=r"points must be a \(\.\.\., 3\)"):
        project_points(_camera(), np.zeros((4, 2)))
