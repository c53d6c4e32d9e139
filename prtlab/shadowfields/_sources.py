"""Incident radiance of local area lights in SH at receiver points (the source radiance of Zhou et al. 2005).

Zhou et al. precompute a *source radiance field* (SRF): the SH of the radiance
arriving from a local light at points on concentric spheres around it, looked
up (trilinear, rotated into the light's pose) at run time. Both forms are here:

* :func:`area_light_sh` evaluates the quantity exactly at each point: the light
  is a parallelogram (``center + s u + t v``, ``s, t in [-1, 1]``) emitting
  ``radiance`` on the side of ``cross(u, v)``, integrated over its area by a
  Gauss-Legendre rule in ``(s, t)``;
* :func:`source_radiance_field` samples it once per light *shape* on the
  sample spheres of :func:`sphere_grid` (in the light's canonical frame, per
  unit radiance), and :meth:`SourceRadianceField.lookup` serves any pose,
  uniform scale and radiance of a light of that shape.

The field trades the exact per-point integral (``n_nodes**2`` light points,
``n*n`` SH each) for an 8-corner blend and an SH rotation; its error is the
interpolation of a field with a discontinuity in the light's plane (behind
the light it is 0), measured in ``tests/shadowfields/test_sources.py``.
Occlusion is not included (multiply by the visibility of :mod:`._direct`).

Point lights (:func:`point_light_direct`) are an exact delta: no field, no SH
projection of the light. Their visibility is needed in one direction only, so
they are routed through the exact or all-frequency visibility (the Haar path,
:func:`prtlab.shadowfields.haar_direct`, or a shadow ray);
:func:`sh_visibility_toward` offers the SH path's smooth visibility and the
tests measure what it costs (a point light's hard shadow seen through order-4
SH visibility is wrong by tens of percent near and inside the shadow).

References
----------
K. Zhou et al., "Precomputed shadow fields for dynamic scenes", SIGGRAPH 2005,
Sec. 3 (source radiance fields) and Sec. 4.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numba
import numpy as np

from prtlab import sh
from prtlab._validate import as_points, check_int, check_order

from ._grid import SphereGrid, interpolate_field, sphere_grid

__all__ = ["area_light_sh", "SourceRadianceField", "source_radiance_field", "point_light_direct",
           "sh_visibility_toward"]


@numba.njit(cache=True, parallel=True)
def _light_samples(points, ys, area_w, normal, dirs, weight):
    """Unit directions to the light points and their solid-angle weights ``dA cos_l / r^2``."""
    for p in numba.prange(points.shape[0]):
        for m in range(ys.shape[0]):
            dx = ys[m, 0] - points[p, 0]
            dy = ys[m, 1] - points[p, 1]
            dz = ys[m, 2] - points[p, 2]
            r2 = dx * dx + dy * dy + dz * dz
            if r2 > 0.0:
                r = np.sqrt(r2)
                dx /= r
                dy /= r
                dz /= r
                cos_l = -(dx * normal[0] + dy * normal[1] + dz * normal[2])
                weight[p, m] = area_w[m] * cos_l / r2 if cos_l > 0.0 else 0.0
                dirs[p, m, 0], dirs[p, m, 1], dirs[p, m, 2] = dx, dy, dz
            else:
                weight[p, m] = 0.0
                dirs[p, m, 0], dirs[p, m, 1], dirs[p, m, 2] = normal[0], normal[1], normal[2]


@functools.lru_cache(maxsize=8)
def _gauss_legendre(n: int):
    return np.polynomial.legendre.leggauss(n)


def area_light_sh(light, points, order: int, n_nodes: int = 12, method: str = "numba") -> np.ndarray:
    """SH of the radiance arriving from an area light at points (unoccluded).

    Parameters
    ----------
    light : prtlab.scene.AreaLight
    points : (..., 3) float
    order : int
    n_nodes : int
        Gauss-Legendre nodes per edge of the parallelogram (``n_nodes**2`` light points).
    method : {"numba", "reference"}
        Light-sample geometry by a parallel kernel or in numpy float64 (the specification).

    Returns
    -------
    coeffs : (..., n*n, 3) float64
        ``int L(p, w) Y_i(w) dw`` per colour channel.

    Notes
    -----
    The solid-angle integral is taken over the light's area,

    .. math::

        \\int L(p, w) Y_i(w) dw = L_e \\int_A Y_i(w_y) \\frac{\\max(0, -n_l \\cdot w_y)}{|y - p|^2} dA_y,
        \\qquad w_y = \\frac{y - p}{|y - p|},

    by a tensor Gauss-Legendre rule over ``(s, t)``; it is accurate for lights
    of any angular size except for points within about an edge / ``n_nodes``
    of the light.
    """
    order = check_order(order)
    check_int(n_nodes, "n_nodes", 1)
    if method not in ("numba", "reference"):
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
    points = as_points(points)
    batch = points.shape[:-1]
    flat = points.reshape(-1, 3)
    x, w = _gauss_legendre(int(n_nodes))
    u, v = np.asarray(light.u, float), np.asarray(light.v, float)
    ys = np.asarray(light.center, float) + x[:, None, None] * u + x[None, :, None] * v
    ys = ys.reshape(-1, 3)
    area_w = (w[:, None] * w[None, :]).reshape(-1) * np.linalg.norm(np.cross(u, v))  # dA = |u x v| ds dt
    normal = light.normal
    out = np.zeros((len(flat), order * order))
    step = max(1, (1 << 20) // len(ys))
    for a in range(0, len(flat), step):
        chunk = np.ascontiguousarray(flat[a : a + step])
        dirs = np.empty((len(chunk), len(ys), 3))
        weight = np.empty((len(chunk), len(ys)))
        if method == "reference":
            d = ys[None, :, :] - chunk[:, None, :]
            r2 = np.sum(d * d, axis=-1)
            r = np.sqrt(r2)
            cos_l = np.maximum(-(d @ normal) / np.where(r > 0, r, 1.0), 0.0)
            weight = np.where(r2 > 0, area_w * cos_l / np.where(r2 > 0, r2, 1.0), 0.0)
            dirs = np.where(r[..., None] > 0, d / np.where(r > 0, r, 1.0)[..., None], normal)
        else:
            _light_samples(chunk, np.ascontiguousarray(ys), area_w, np.asarray(normal, float), dirs, weight)
        out[a : a + step] = np.einsum("pm,pmi->pi", weight, sh.basis(dirs, order))
    return (out[:, :, None] * np.asarray(light.radiance, float)).reshape(batch + (order * order, 3))


def _canonical(light) -> tuple[np.ndarray, np.ndarray]:
    """The light's frame ``F`` (columns ``e1 = u / |u|``, ``e2 = e3 x e1``, ``e3`` its normal) and its shape
    ``(|u|, v . e1, v . e2)``: in ``F`` the light is ``s (|u|, 0, 0) + t (v . e1, v . e2, 0)``."""
    u, v = np.asarray(light.u, dtype=np.float64), np.asarray(light.v, dtype=np.float64)
    nu = float(np.linalg.norm(u))
    normal = np.cross(u, v)
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(v))) or nu == 0 or np.linalg.norm(normal) == 0:
        raise ValueError(f"the area light's u and v must be finite, non-zero and not parallel, got u={u}, v={v}")
    e1, e3 = u / nu, normal / np.linalg.norm(normal)
    frame = np.stack([e1, np.cross(e3, e1), e3], axis=1)
    return frame, np.array([nu, v @ frame[:, 0], v @ frame[:, 1]])


@dataclass(frozen=True)
class SourceRadianceField:
    """The SH radiance of a unit-radiance area light sampled on concentric spheres (Zhou et al. 2005 Sec. 3).

    Attributes
    ----------
    grid : SphereGrid
        Sample spheres about the light's centre, in its canonical frame (:func:`source_radiance_field`).
    order : int
    shape : (3,) float64
        ``(|u|, v . e1, v . e2)`` of the light it was built for; lights of this shape up to a uniform
        scale share the field.
    coeffs : (n_r, 6, res, res, order**2) float64
        ``int L(p, w) Y_i(w) dw`` for radiance 1 at every grid point.
    """

    grid: SphereGrid
    order: int
    shape: np.ndarray
    coeffs: np.ndarray

    def fits(self, light) -> bool:
        """Whether ``light`` has the field's shape up to a uniform scale."""
        _, shape = _canonical(light)
        return bool(np.allclose(shape, shape[0] / self.shape[0] * self.shape, rtol=0.0, atol=1e-9 * shape[0]))

    def lookup(self, light, points, method: str = "numba") -> np.ndarray:
        """SH of the radiance arriving from ``light`` at world points (unoccluded), as :func:`area_light_sh`.

        Parameters
        ----------
        light : prtlab.scene.AreaLight
            Any pose, size (a uniform scale of the field's light) and radiance.
        points : (..., 3) float
        method : {"numba", "reference"}
            Interpolation tier (:func:`interpolate_field`).

        Returns
        -------
        coeffs : (..., order**2, 3) float64
            Beyond the outermost sphere, the outermost sphere's value in the point's direction times
            ``(r_max / r)^2`` (the light's solid angle falls off as ``1 / r^2``).

        Notes
        -----
        With ``F`` the light's frame, ``c`` its centre and ``a`` its scale relative to the field's
        light, the field is read at ``F^T (p - c) / a`` (solid angles are invariant under a uniform
        scale of the whole configuration) and rotated by ``F``: ``L_world(w) = L_canonical(F^T w)``.
        """
        if not self.fits(light):
            raise ValueError("the area light's shape (|u|, |v| and their angle) is not a uniform scale of the "
                             "field's; build a field for it with source_radiance_field(light)")
        points = as_points(points)
        frame, shape = _canonical(light)
        local = (points - np.asarray(light.center, dtype=np.float64)) @ frame / (shape[0] / self.shape[0])
        out, _ = interpolate_field(self.grid, self.coeffs, local, method=method)
        if out.size:
            r = np.linalg.norm(local - self.grid.center, axis=-1)
            out *= ((self.grid.radii[-1] / np.maximum(r, self.grid.radii[-1])) ** 2)[..., None]
            out = sh.rotate(out.reshape(-1, out.shape[-1]), frame, channels=False).reshape(out.shape)
        return out[..., None] * np.asarray(light.radiance, dtype=np.float64)

    def to_arrays(self) -> dict:
        return {"grid": self.grid.to_arrays(), "order": np.int64(self.order), "shape": self.shape,
                "coeffs": self.coeffs}

    @classmethod
    def from_arrays(cls, d) -> "SourceRadianceField":
        return cls(SphereGrid.from_arrays(d["grid"]), int(d["order"]), np.asarray(d["shape"], float),
                   np.asarray(d["coeffs"], float))


def source_radiance_field(light, order: int = 4, *, n_radii: int = 16, resolution: int = 16, r_min: float = 0.2,
                          r_max: float = 8.0, spacing: str = "geometric", n_nodes: int = 12) -> SourceRadianceField:
    """Precompute the source radiance field of an area light's shape (Zhou et al. 2005, Sec. 3).

    Parameters
    ----------
    light : prtlab.scene.AreaLight
        Only its shape matters (``|u|``, ``|v|`` and their angle); pose and radiance are given at lookup.
    order : int
    n_radii, resolution, r_min, r_max, spacing
        The sample spheres about the light's bounding sphere (:func:`sphere_grid`).
    n_nodes : int
        Gauss-Legendre nodes per edge of :func:`area_light_sh` at the grid points (12; 24 changes the
        field's error against the exact projection by less than 1e-9).

    Returns
    -------
    SourceRadianceField

    Examples
    --------
    >>> from prtlab.scene import AreaLight
    >>> light = AreaLight(np.zeros(3), np.array([0.5, 0, 0]), np.array([0, 0.5, 0]), np.ones(3))
    >>> srf = source_radiance_field(light, 2, n_radii=2, resolution=2)
    >>> srf.coeffs.shape, srf.lookup(light, [0.0, 0.0, 1.0]).shape
    ((2, 6, 2, 2, 4), (4, 3))
    """
    from prtlab.scene import AreaLight

    order = check_order(order)
    _, shape = _canonical(light)
    u, v = np.array([shape[0], 0.0, 0.0]), np.array([shape[1], shape[2], 0.0])
    corners = np.array([su * u + sv * v for su in (-1, 1) for sv in (-1, 1)])
    grid = sphere_grid((corners, np.zeros((0, 3), dtype=np.int64)), n_radii, resolution, r_min, r_max, spacing)
    unit = AreaLight(center=np.zeros(3), u=u, v=v, radiance=np.ones(3))
    coeffs = area_light_sh(unit, grid.points(), order, n_nodes=n_nodes)[..., 0]
    return SourceRadianceField(grid, order, shape, coeffs)


def sh_visibility_toward(visibility, dirs) -> np.ndarray:
    """The SH visibility evaluated in given directions, clamped to [0, 1] (the smooth visibility of the SH path).

    Parameters
    ----------
    visibility : (V, n*n) float
        SH visibility per vertex (:func:`visibility_pass`).
    dirs : (V, 3) float
        A direction per vertex (e.g. toward a point light; normalised here).

    Returns
    -------
    values : (V,) float64
        ``clip(sum_i V_i Y_i(d), 0, 1)``. Order-n SH blur a shadow edge over about
        ``pi / n`` radians and ring around it: a point light's shadow, which
        needs the visibility in exactly one direction, is the worst case of the SH
        path (measured in ``tests/shadowfields/test_sources.py``); prefer the
        visibility of the Haar path (:func:`haar_direct`) or a shadow ray.
    """
    vis = np.asarray(visibility, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    if vis.ndim != 2:
        raise ValueError(f"visibility must be (V, n*n), got shape {vis.shape}")
    order = int(round(np.sqrt(vis.shape[1])))
    if order * order != vis.shape[1] or order < 1:
        raise ValueError(f"visibility must have n*n coefficients, got {vis.shape[1]}")
    if d.shape != (len(vis), 3):
        raise ValueError(f"dirs must be (V, 3) = ({len(vis)}, 3), got shape {d.shape}")
    if not (np.all(np.isfinite(vis)) and np.all(np.isfinite(d))):
        raise ValueError("visibility or dirs contain NaN or inf")
    if len(vis) == 0:
        return np.zeros(0)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(norm > 0, d / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))
    return np.clip(np.einsum("vi,vi->v", vis, sh.basis(d, order)), 0.0, 1.0)


def point_light_direct(light, points, normals, sep, visibility=None) -> np.ndarray:
    """Direct light ``L_k`` (V, K, C) of a point light through a separable BRDF: an exact delta.

    ``L_k = I / r^2 g_k(d) max(0, n . d) V(d)`` with ``d`` the unit direction to the light.
    Point lights need the visibility in one direction only, so both paths take it
    from the exact or all-frequency visibility: :func:`haar_direct` (the texel of
    ``d`` in the Haar visibility) or a shadow ray; :func:`sh_visibility_toward`
    gives the SH path's smooth visibility, at a cost measured in the tests.

    Parameters
    ----------
    light : prtlab.scene.PointLight
    points, normals : (V, 3) float
    sep : prtlab.brdf.SeparableBRDF
        ``"plain"``; ``g_k`` in the frame of :func:`prtlab.brdf.local_frame`.
    visibility : (V,) float, optional
        Visibility toward the light in [0, 1] (default 1: unoccluded).

    Returns
    -------
    light_k : (V, K, 3) float64
    """
    from prtlab.brdf import SeparableBRDF, to_local

    if not isinstance(sep, SeparableBRDF):
        raise TypeError(f"sep must be a SeparableBRDF (prtlab.brdf.separable), got {type(sep).__name__}")
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points and normals must be (V, 3) arrays of one shape, got {points.shape} and "
                         f"{normals.shape}")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(normals))):
        raise ValueError("points or normals contain NaN or inf")
    vis = np.ones(len(points)) if visibility is None else np.asarray(visibility, dtype=np.float64)
    if vis.shape != (len(points),):
        raise ValueError(f"visibility must be (V,) = ({len(points)},), got shape {vis.shape}")
    if len(points) == 0:
        return np.zeros((0, sep.K, 3))
    d = np.asarray(light.position, float) - points
    r2 = np.einsum("vi,vi->v", d, d)
    safe = np.where(r2 > 0, r2, 1.0)
    unit = np.where(r2[:, None] > 0, d / np.sqrt(safe)[:, None], normals)
    n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    cos = np.maximum(np.einsum("vi,vi->v", unit, n), 0.0)
    g = sep.g(to_local(unit, n))
    weight = np.where(r2 > 0, cos / safe, 0.0) * vis
    return (g * weight[:, None])[..., None] * np.asarray(light.intensity, float)
