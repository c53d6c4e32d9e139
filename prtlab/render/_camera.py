"""The pinhole camera: pixel coordinates <-> world rays.

Conventions (the same as Mitsuba's ``perspective`` sensor with
``fov_axis = "y"``, so prtlab images and Mitsuba images line up pixel for
pixel):

- ``fov_deg`` is the *vertical* field of view; ``resolution = (w, h)``.
- Continuous pixel coordinates ``(x, y)``: ``x`` to the right in ``[0, w]``,
  ``y`` down in ``[0, h]``; pixel ``(row i, column j)`` has its centre at
  ``(j + 0.5, i + 0.5)``. Row 0 is the top of the image.
- With ``f = normalize(look_at - position)``, ``r = normalize(f x up)``,
  ``u = r x f`` and ``t = tan(fov / 2)``, the ray through ``(x, y)`` is
  ``normalize(f + (2 x / w - 1) t (w / h) r + (1 - 2 y / h) t u)``.
"""

from __future__ import annotations

import numpy as np

from prtlab.scene import Camera

__all__ = ["camera_frame", "pixel_directions", "camera_rays", "project_points"]


def _check_camera(camera) -> tuple[np.ndarray, int, int, float]:
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a prtlab.scene.Camera, got {type(camera).__name__}")
    try:
        width, height = (int(r) for r in camera.resolution)
    except (TypeError, ValueError):
        raise ValueError(f"camera.resolution must be (width, height), got {camera.resolution!r}") from None
    if width < 1 or height < 1:
        raise ValueError(f"camera.resolution must be positive (width, height), got {camera.resolution!r}")
    fov = float(camera.fov_deg)
    if not 0.0 < fov < 180.0:
        raise ValueError(f"camera.fov_deg must be in (0, 180) degrees (vertical field of view), got {fov}")
    return camera_frame(camera), width, height, fov


def camera_frame(camera) -> np.ndarray:
    """Orthonormal camera frame.

    Returns
    -------
    frame : (3, 3) float64
        Rows ``right``, ``up``, ``forward`` (a right-handed basis with the camera
        looking along ``forward``).
    """
    position = np.asarray(camera.position, dtype=np.float64)
    target = np.asarray(camera.look_at, dtype=np.float64)
    up = np.asarray(camera.up, dtype=np.float64)
    if not (np.all(np.isfinite(position)) and np.all(np.isfinite(target)) and np.all(np.isfinite(up))):
        raise ValueError("camera position, look_at and up must be finite 3-vectors")
    forward = target - position
    norm = np.linalg.norm(forward)
    if norm == 0.0:
        raise ValueError("camera.look_at equals camera.position: the view direction is undefined")
    forward /= norm
    right = np.cross(forward, up)
    rnorm = np.linalg.norm(right)
    if rnorm < 1e-12 * max(np.linalg.norm(up), 1e-300):
        raise ValueError("camera.up is parallel to the view direction; give an up vector that is not")
    right /= rnorm
    true_up = np.cross(right, forward)
    return np.stack([right, true_up, forward])


def pixel_directions(camera, x, y) -> np.ndarray:
    """Unit ray directions through continuous pixel coordinates.

    Parameters
    ----------
    camera : prtlab.scene.Camera
    x, y : (...) float
        Pixel coordinates (``x`` right, ``y`` down, ``(0, 0)`` the top-left image corner).

    Returns
    -------
    dirs : (..., 3) float64
    """
    frame, width, height, fov = _check_camera(camera)
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    t = np.tan(np.radians(fov) / 2.0)
    sx = (2.0 * x / width - 1.0) * t * (width / height)
    sy = (1.0 - 2.0 * y / height) * t
    d = frame[2] + sx[..., None] * frame[0] + sy[..., None] * frame[1]
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def camera_rays(camera) -> tuple[np.ndarray, np.ndarray]:
    """Primary rays through every pixel centre.

    Returns
    -------
    origins : (h, w, 3) float64
    dirs : (h, w, 3) float64
        Unit directions; ``dirs[i, j]`` passes through pixel centre ``(j + 0.5, i + 0.5)``.
    """
    _, width, height, _ = _check_camera(camera)
    y, x = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    dirs = pixel_directions(camera, x, y)
    origins = np.broadcast_to(np.asarray(camera.position, dtype=np.float64), dirs.shape).copy()
    return origins, dirs


def project_points(camera, points) -> tuple[np.ndarray, np.ndarray]:
    """World points to continuous pixel coordinates (the inverse of :func:`pixel_directions`).

    Parameters
    ----------
    points : (..., 3) float

    Returns
    -------
    xy : (..., 2) float64
        Pixel coordinates (NaN for points behind the camera).
    depth : (...) float64
        Distance along the view axis (``<= 0``: behind the camera).
    """
    frame, width, height, fov = _check_camera(camera)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim == 0 or p.shape[-1] != 3:
        raise ValueError(f"points must be a (..., 3) array, got shape {p.shape}")
    rel = p - np.asarray(camera.position, dtype=np.float64)
    local = rel @ frame.T
    depth = local[..., 2]
    t = np.tan(np.radians(fov) / 2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        sx = local[..., 0] / depth / (t * width / height)
        sy = local[..., 1] / depth / t
    x = (sx + 1.0) * width / 2.0
    y = (1.0 - sy) * height / 2.0
    xy = np.stack([x, y], axis=-1)
    xy[depth <= 0] = np.nan
    return xy, depth
