"""Images of per-vertex radiance: primary rays, barycentric interpolation, sky and lights.

Every method in prtlab produces radiance at mesh vertices; this module turns
it into a picture the way the papers' shaders do (Gouraud interpolation),
with the environment as background and area lights visible from the front.
"""

from __future__ import annotations

import numpy as np

from prtlab.scene import Scene, ShadeResult

from ._camera import camera_rays

__all__ = ["render_image", "interpolate_vertex_values", "barycentric_coordinates", "intersect_area_lights"]

_PARTS = ("direct", "indirect", "total")


def barycentric_coordinates(origins, dirs, a, b, c) -> tuple[np.ndarray, np.ndarray]:
    """Ray/triangle-plane intersection in float64 (Moller-Trumbore, no inside test).

    Parameters
    ----------
    origins, dirs : (n, 3) float
    a, b, c : (n, 3) float
        Triangle corners.

    Returns
    -------
    bary : (n, 3) float64
        Weights of ``(a, b, c)``; they sum to one and reproduce the hit point.
    t : (n,) float64
        Ray parameter of the plane hit (NaN for rays parallel to the plane).
    """
    e1 = b - a
    e2 = c - a
    pvec = np.cross(dirs, e2)
    det = np.einsum("ij,ij->i", e1, pvec)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(det != 0.0, 1.0 / det, np.nan)
        tvec = origins - a
        u = np.einsum("ij,ij->i", tvec, pvec) * inv
        qvec = np.cross(tvec, e1)
        v = np.einsum("ij,ij->i", dirs, qvec) * inv
        t = np.einsum("ij,ij->i", e2, qvec) * inv
    return np.stack([1.0 - u - v, u, v], axis=1), t


def interpolate_vertex_values(faces, values, triangle, bary) -> np.ndarray:
    """Barycentric interpolation of per-vertex values.

    Parameters
    ----------
    faces : (n_faces, 3) int
    values : (n_vertices, C) float
    triangle : (n,) int
        Face index of each sample.
    bary : (n, 3) float
        Barycentric weights of the face's three vertices.

    Returns
    -------
    out : (n, C) float64
    """
    faces = np.asarray(faces)
    values = np.asarray(values, dtype=np.float64)
    corners = faces[np.asarray(triangle)]
    return np.einsum("nk,nkc->nc", np.asarray(bary, dtype=np.float64), values[corners])


def intersect_area_lights(lights, origins, dirs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest hit of rays with the scene's area-light parallelograms.

    Parameters
    ----------
    lights : sequence of AreaLight
    origins, dirs : (n, 3) float

    Returns
    -------
    t : (n,) float64
        Distance to the closest light (``inf`` if none).
    index : (n,) int64
        Which light (``-1`` if none).
    front : (n,) bool
        Whether the ray meets the emitting side (``dirs . normal < 0``).
    """
    n = len(origins)
    best = np.full(n, np.inf)
    index = np.full(n, -1, dtype=np.int64)
    front = np.zeros(n, dtype=bool)
    for k, light in enumerate(lights):
        u, v, c = (np.asarray(x, dtype=np.float64) for x in (light.u, light.v, light.center))
        normal = np.cross(u, v)
        denom = dirs @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((c - origins) @ normal) / denom
        p = origins + t[:, None] * dirs - c
        # solve p = s u + r v in the plane (u, v need not be orthogonal)
        g = np.array([[u @ u, u @ v], [u @ v, v @ v]])
        rhs = np.stack([p @ u, p @ v], axis=1)
        st = np.linalg.solve(g, rhs.T).T
        ok = (denom != 0) & (t > 0) & (np.abs(st[:, 0]) <= 1.0) & (np.abs(st[:, 1]) <= 1.0) & (t < best)
        best = np.where(ok, t, best)
        index = np.where(ok, k, index)
        front = np.where(ok, denom < 0, front)
    return best, index, front


def _object_values(values: dict, obj, part: str) -> np.ndarray:
    """``values[obj.name]`` as a float64 ``(n_vertices, 3)`` array; a KeyError / ValueError naming ``part``."""
    if obj.name not in values:
        raise KeyError(
            f"result has no {part!r} radiance for object {obj.name!r}, which the camera sees; "
            f"it has {sorted(values)}"
        )
    vals = np.asarray(values[obj.name], dtype=np.float64)
    if vals.shape != (obj.n_vertices, 3):
        raise ValueError(f"result.{part}[{obj.name!r}] must have shape ({obj.n_vertices}, 3), got {vals.shape}")
    return vals


def render_image(scene, result, part: str = "total", *, background: bool = True) -> np.ndarray:
    """Render per-vertex radiance from the scene camera.

    Parameters
    ----------
    scene : prtlab.Scene
    result : ShadeResult
        Per-vertex radiance of (at least) every visible object.
    part : {"total", "direct", "indirect"}
    background : bool
        Show the environment (and area lights) where no object is hit; False gives black.

    Returns
    -------
    image : (h, w, 3) float64
        Linear RGB; row 0 is the top of the image.

    Notes
    -----
    One primary ray through each pixel centre (:func:`prtlab.render.camera_rays`),
    closest hit by :class:`prtlab.geometry.RayCaster` (Embree), then in float64
    ``L = b_a L_a + b_b L_b + b_c L_c`` with the hit's barycentrics recomputed
    from the ray and the float64 triangle, so a per-vertex function linear over
    each triangle is reproduced exactly. Rays that miss show the environment
    radiance ``L_env(d)`` (black without environment). An area light in front
    of everything shows its radiance from the emitting side and black from
    behind (it reflects nothing).
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a prtlab.Scene, got {type(scene).__name__}")
    if not isinstance(result, ShadeResult):
        raise TypeError(f"result must be a prtlab.ShadeResult (from prtlab.shade), got {type(result).__name__}")
    if part not in _PARTS:
        raise ValueError(f"part must be one of {_PARTS}, got {part!r}")
    from prtlab.geometry import RayCaster

    origins, dirs = camera_rays(scene.camera)
    height, width = dirs.shape[:2]
    o = origins.reshape(-1, 3)
    d = dirs.reshape(-1, 3)
    image = np.zeros((len(d), 3))
    values = getattr(result, part)

    caster = RayCaster(scene)
    hits = caster.closest_hit(o, d)
    t_mesh = np.where(hits.hit, hits.distance, np.inf)
    for k in range(caster.n_objects):
        obj = scene.objects[caster.object_index[k]]
        sel = np.nonzero(hits.hit & (hits.object == k))[0]
        if len(sel) == 0:
            continue
        vals = _object_values(values, obj, part)
        faces = caster.faces(k)
        verts = caster.world_vertices(k)
        tri = hits.triangle[sel]
        f = faces[tri]
        bary, _ = barycentric_coordinates(o[sel], d[sel], verts[f[:, 0]], verts[f[:, 1]], verts[f[:, 2]])
        image[sel] = interpolate_vertex_values(faces, vals, tri, bary)

    t_light, which, front = intersect_area_lights(scene.area_lights, o, d)
    light_hit = t_light < t_mesh
    if background:
        lights = scene.area_lights
        for k, light in enumerate(lights):
            sel = light_hit & (which == k)
            image[sel] = np.where(front[sel, None], np.asarray(light.radiance, dtype=np.float64), 0.0)
        env = scene.environment
        miss = ~hits.hit & ~light_hit
        if env is not None and np.any(miss):
            image[miss] = env.radiance(d[miss])
    else:
        image[light_hit] = 0.0
    return image.reshape(height, width, 3)
