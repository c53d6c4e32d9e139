"""A flat occluder's visibility near its plane (an extension of Iwasaki et al. 2007; option
``flat_visibility="plane"``).

An occlusion field is sampled on spheres about its object's centre and interpolated between the samples. Close
to a flat occluder's plane the interpolation mixes samples from both sides of it, so that a point resting on a
ground sees the ground half as well as it should: a box on a floor under a sky got 44 % too little direct light
along its bottom row (``docs/notes/interreflection.md``). There the plane hides nearly a half-space: from a point
at height ``h`` over the plane, inside its footprint and at distance ``d`` from the footprint's boundary (holes
included), it hides every direction below the horizon but for a band of elevation less than ``atan(h / d)``
beside the horizon. Where ``|h| < NEAR_RATIO d`` the field's value is replaced by the order-n SH projection of
that half-space (:func:`halfspace_zh`, rotated to the side the point is on; in the plane, the side its normals
face). What stays is the band limit of the order-n light against a hard horizon: about 13 % too little light on
a face standing on the plane under a clear sky at order 4, where the field's blur, by chance, gave 10 % too
little 5 cm above the plane (measured in the notes).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import trimesh
from scipy.special import eval_legendre

from prtlab import sh

#: The largest ``|h| / d`` at which a point takes the half-space: the band it adds below the horizon is under
#: ``atan(0.05)``, 2.9 degrees of elevation. (A vertex resting on the plane is shaded a third of a percent of an
#: edge above it, :mod:`prtlab.geometry._shading`.)
NEAR_RATIO = 0.05


def halfspace_zh(order: int) -> np.ndarray:
    """ZH coefficients (order,) of the indicator of the hemisphere ``cos theta > 0``: ``z_l = 2 pi sqrt((2l+1) /
    (4 pi)) int_0^1 P_l(t) dt``, the integral ``1`` for ``l = 0`` and ``(P_(l-1)(0) - P_(l+1)(0)) / (2l + 1)``
    above."""
    z = np.empty(order)
    for band in range(order):
        integral = 1.0 if band == 0 else (eval_legendre(band - 1, 0.0) - eval_legendre(band + 1, 0.0)) / (2 * band + 1)
        z[band] = 2.0 * math.pi * math.sqrt((2 * band + 1) / (4.0 * math.pi)) * integral
    return z


class FlatOccluder:
    """A flat mesh in its object space: a point on its plane, its unit normal (the side its vertex normals face),
    two unit axes in the plane and its footprint's boundary edges in those axes' coordinates."""

    def __init__(self, vertices, faces, normals):
        v = np.asarray(vertices, dtype=np.float64)
        self.centre = v.mean(axis=0)
        _, _, vt = np.linalg.svd(v - self.centre, full_matrices=False)
        normal = vt[2] if np.dot(vt[2], np.mean(normals, axis=0)) >= 0.0 else -vt[2]
        self.normal, self.axes = normal, vt[:2]
        faces = np.asarray(faces)
        edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        boundary = edges[trimesh.grouping.group_rows(edges, require_count=1)]  # edges of one face
        flat = (v - self.centre) @ self.axes.T
        self.a, self.b = flat[boundary[:, 0]], flat[boundary[:, 1]]
        self.lo, self.hi = flat.min(axis=0), flat.max(axis=0)
        self.radius = float(np.linalg.norm(flat, axis=1).max())  # (for the in-plane tolerance)

    def near(self, points, transform, method: str = "numba") -> tuple[np.ndarray, np.ndarray]:
        """``(rows, axes)``: the world ``points`` where the occluder, placed by ``transform``, takes its half-space
        (``|h| < NEAR_RATIO d``, inside its footprint) and each one's visible side (world unit vectors; within a
        rounding of the plane, ``1e-9`` of its size, the side its normals face)."""
        rot, scale = np.asarray(transform.rotation, dtype=np.float64), float(transform.scale)
        local = (np.asarray(points, dtype=np.float64) - np.asarray(transform.translate, dtype=np.float64)) @ rot / scale
        h = (local - self.centre) @ self.normal
        p = (local - self.centre) @ self.axes.T
        # inside the footprint, d is at most the distance to its bounding box's sides: a first cut
        box = np.minimum(p - self.lo, self.hi - p).min(axis=1)
        rows = np.flatnonzero(np.abs(h) < NEAR_RATIO * box)
        if len(rows):
            rows = rows[self.taken(p[rows], h[rows], method)]
        side = np.where(h[rows, None] >= -1e-9 * self.radius, self.normal, -self.normal)  # in the plane: in front
        return rows, side @ rot.T

    def taken(self, p, h, method: str = "numba") -> np.ndarray:
        """(P,) bool: the points at footprint coordinates ``p`` (P, 2) and heights ``h`` (P,) inside the footprint
        with ``|h| < NEAR_RATIO d``. ``method``: a serial kernel (``"numba"``) or numpy (``"reference"``)."""
        if method == "reference":
            return self._inside(p) & (np.abs(h) < NEAR_RATIO * self._boundary_distance(p))
        out = np.empty(len(p), dtype=np.bool_)
        _taken_kernel(np.ascontiguousarray(p, dtype=np.float64), np.ascontiguousarray(h, dtype=np.float64),
                      self.a, self.b, NEAR_RATIO, out)
        return out

    def _boundary_distance(self, p) -> np.ndarray:
        ab = self.b - self.a
        t = np.clip(np.einsum("pei,ei->pe", p[:, None] - self.a, ab) / np.maximum(np.einsum("ei,ei->e", ab, ab),
                                                                                   1e-300), 0.0, 1.0)
        gap = p[:, None] - (self.a + t[..., None] * ab)
        return np.sqrt(np.einsum("pei,pei->pe", gap, gap).min(axis=1))

    def _inside(self, p) -> np.ndarray:
        """Even-odd rule over the boundary edges (a footprint with holes too)."""
        ay, by = self.a[:, 1], self.b[:, 1]
        crosses = (ay > p[:, 1:2]) != (by > p[:, 1:2])
        with np.errstate(divide="ignore", invalid="ignore"):
            x_at = self.a[:, 0] + (p[:, 1:2] - ay) * (self.b[:, 0] - self.a[:, 0]) / (by - ay)
        return np.count_nonzero(crosses & (p[:, 0:1] < x_at), axis=1) % 2 == 1


def halfspace_visibility(axes, order: int, log_floor: float | None = None) -> np.ndarray:
    """(P, order^2) SH visibility of the half-spaces toward ``axes`` (P, 3); with ``log_floor`` its SH log as
    :func:`prtlab.shadowfields.log_occlusion_field` takes an occlusion field's (``exp*(g) = floor + (1 - floor)
    V``; the log of a zonal function is zonal)."""
    zh = halfspace_zh(order)
    if log_floor is not None:
        up = sh.zh_rotate(zh, np.array([0.0, 0.0, 1.0]))
        one = np.zeros_like(up)
        one[0] = math.sqrt(4.0 * math.pi)
        log = sh.log((1.0 - log_floor) * up + log_floor * one, channels=False, tol=1e-6, degree=8 * order - 1)
        zh = log[[sh.index(band, 0) for band in range(order)]]  # about z: c_l0 = z_l
    return sh.zh_rotate(zh, np.asarray(axes, dtype=np.float64).reshape(-1, 3))


@numba.njit(cache=True, nogil=True)
def _taken_kernel(p, h, a, b, ratio, out):
    """:meth:`FlatOccluder.taken` point by point: the even-odd crossings and the nearest boundary edge."""
    for i in range(len(p)):
        px, py = p[i, 0], p[i, 1]
        crossings = 0
        best = np.inf
        for e in range(len(a)):
            ax, ay, bx, by = a[e, 0], a[e, 1], b[e, 0], b[e, 1]
            if (ay > py) != (by > py) and px < ax + (py - ay) * (bx - ax) / (by - ay):
                crossings += 1
            dx, dy = bx - ax, by - ay
            t = ((px - ax) * dx + (py - ay) * dy) / max(dx * dx + dy * dy, 1e-300)
            t = min(max(t, 0.0), 1.0)
            gx, gy = px - (ax + t * dx), py - (ay + t * dy)
            best = min(best, gx * gx + gy * gy)
        out[i] = crossings % 2 == 1 and abs(h[i]) < ratio * np.sqrt(best)
