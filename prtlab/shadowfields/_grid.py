"""Sample points on concentric spheres around an object, and trilinear lookups of fields stored there.

Zhou et al. 2005 (Sec. 3) sample a shadow field at points on concentric
spheres around an object; Iwasaki et al. 2007 (Sec. 3.1, 6) use 16 spheres of
``6 x 16 x 16`` points each. Here the points of one sphere sit in the
directions of the texel centres of a ``resolution``-cubemap
(:func:`prtlab.geometry.cubemap_directions`), so a point's direction cell is
found by :func:`prtlab.geometry.direction_to_cubemap`, the one place the
cubemap convention lives.

Interpolation (run time)
    A query point ``q`` (object space) has radius ``r = |q - c|`` and
    direction ``d = (q - c) / r``. Its fractional sphere index is the
    piecewise-linear inverse of the radii (``np.interp``), its face
    coordinates ``(s, t)`` those of ``d``; the value is the trilinear blend of
    the 8 nearest samples (2 spheres x 2 x 2 texels of the face). At face
    borders (within half a texel of an edge) the texel coordinate is clamped,
    so the blend there is linear in one direction only; radii below the
    innermost sphere are clamped to it. Points beyond the outermost sphere are
    reported (``beyond``) so the caller can treat them (an occlusion field
    treats them as unoccluded).

Radii
    ``spacing="geometric"`` (default) spaces the radii geometrically between
    ``r_min`` and ``r_max`` (multiples of the bounding radius ``R``): the
    angular size of an object seen from distance ``r`` varies like ``R / r``,
    so equal ratios give equal relative change between neighbouring spheres.
    ``spacing="uniform"`` is the equal spacing of Iwasaki et al. Sec. 3.1.
    The default ``r_min = 0.2 R`` follows Zhou et al. (receivers near a
    large object, e.g. a floor under a bunny, lie inside its bounding sphere);
    ``r_max = 8 R``: beyond it a whole object blocks at most
    ``(1 - cos(asin(1/8))) / 2 = 0.4 %`` of the sphere of directions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prtlab._validate import as_points, check_int
from prtlab.geometry import cubemap_directions, direction_to_cubemap

from ._kernels import locate_kernel, trilinear_kernel

__all__ = ["SphereGrid", "sphere_grid", "interpolate_field", "bounding_sphere"]

_SPACINGS = ("geometric", "uniform")


def bounding_sphere(vertices) -> tuple[np.ndarray, float]:
    """Centre (bounding-box centre) and radius (farthest vertex from it) of a point set."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if len(v) == 0:
        raise ValueError("the mesh has no vertices; a sphere grid needs a non-empty mesh")
    center = 0.5 * (v.min(axis=0) + v.max(axis=0))
    radius = float(np.max(np.linalg.norm(v - center, axis=1)))
    return center, max(radius, 1e-12)


@dataclass(frozen=True)
class SphereGrid:
    """Sample points on concentric spheres, in the object space of one object.

    Attributes
    ----------
    center : (3,) float64
        Centre of the bounding sphere.
    radius : float
        Bounding radius ``R``.
    radii : (n_r,) float64
        Increasing absolute radii of the sample spheres.
    resolution : int
        Points per cubemap face edge: ``6 * resolution**2`` points per sphere.
    """

    center: np.ndarray
    radius: float
    radii: np.ndarray
    resolution: int

    @property
    def n_points(self) -> int:
        return len(self.radii) * 6 * self.resolution**2

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """``(n_r, 6, res, res)``: the leading axes of a field sampled on the grid."""
        return (len(self.radii), 6, self.resolution, self.resolution)

    def directions(self) -> np.ndarray:
        """(6, res, res, 3) unit directions of the points of every sphere."""
        return cubemap_directions(self.resolution)

    def points(self) -> np.ndarray:
        """(n_r, 6, res, res, 3) sample points in object space."""
        return self.center + self.radii[:, None, None, None, None] * self.directions()[None]

    def locate(self, points, method: str = "numba") -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                              np.ndarray]:
        """Fractional sphere index, face, face coordinates and the ``beyond`` mask of object-space points: by one
        kernel (``"numba"``, :func:`locate_kernel`) or by numpy (``"numpy"``, the specification): the same values,
        bit for bit.

        Returns
        -------
        rpos : (Q,) float64 in [0, n_r - 1]
        face : (Q,) int64
        s, t : (Q,) float64
        beyond : (Q,) bool
            ``r > radii[-1]``.
        """
        if method not in ("numba", "numpy"):
            raise ValueError(f"method must be 'numba' or 'numpy', got {method!r}")
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if method == "numba" and len(self.radii) >= 2 and np.all(np.isfinite(points)):  # else numpy's checks
            out = (np.empty(len(points)), np.empty(len(points), np.int64), np.empty(len(points)), np.empty(len(points)),
                   np.empty(len(points), np.bool_))
            locate_kernel(np.ascontiguousarray(points), np.asarray(self.center, np.float64),
                          np.ascontiguousarray(self.radii, np.float64), *out)
            return out
        p = points - self.center
        r = np.linalg.norm(p, axis=1)
        d = np.where(r[:, None] > 0, p, np.array([0.0, 0.0, 1.0]))
        face, s, t = direction_to_cubemap(d)
        rpos = np.interp(r, self.radii, np.arange(len(self.radii), dtype=np.float64))
        return rpos, face, s, t, r > self.radii[-1]

    def trilinear_corners(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The 8 samples of the trilinear blend at object-space points (as :func:`interpolate_field`: radius
        clamped to the first and last sphere, face coordinates clamped to the face's texel centres).

        Returns
        -------
        corners : (Q, 8) int64
            Flat indices into the ``(n_r, 6, res, res)`` samples.
        weights : (Q, 8) float64
            Blend weights (summing to 1).
        beyond : (Q,) bool
            ``r > radii[-1]``.
        """
        rpos, face, s, t, beyond = self.locate(points)
        n_r, _, g, _ = self.shape
        r0 = np.clip(np.floor(rpos).astype(np.int64), 0, n_r - 1)
        fr = rpos - r0
        r1 = np.minimum(r0 + 1, n_r - 1)
        x = np.clip(s * g - 0.5, 0.0, g - 1.0)
        y = np.clip(t * g - 0.5, 0.0, g - 1.0)
        j0 = np.floor(x).astype(np.int64)
        i0 = np.floor(y).astype(np.int64)
        fj, fi = x - j0, y - i0
        j1 = np.minimum(j0 + 1, g - 1)
        i1 = np.minimum(i0 + 1, g - 1)
        corners = np.empty((len(rpos), 8), dtype=np.int64)
        weights = np.empty((len(rpos), 8))
        c = 0
        for rr, wr in ((r0, 1.0 - fr), (r1, fr)):
            for ii, wi in ((i0, 1.0 - fi), (i1, fi)):
                for jj, wj in ((j0, 1.0 - fj), (j1, fj)):
                    corners[:, c] = ((rr * 6 + face) * g + ii) * g + jj
                    weights[:, c] = wr * wi * wj
                    c += 1
        return corners, weights, beyond

    def to_arrays(self) -> dict:
        return {"center": self.center, "radius": np.float64(self.radius), "radii": self.radii,
                "resolution": np.int64(self.resolution)}

    @classmethod
    def from_arrays(cls, d) -> "SphereGrid":
        return cls(np.asarray(d["center"], float), float(d["radius"]), np.asarray(d["radii"], float),
                   int(d["resolution"]))


def sphere_grid(mesh, n_radii: int = 16, resolution: int = 16, r_min: float = 0.2, r_max: float = 8.0,
                spacing: str = "geometric") -> SphereGrid:
    """Concentric sample spheres around a mesh (object space).

    Parameters
    ----------
    mesh : trimesh.Trimesh or (vertices, faces)
    n_radii : int >= 1
        Number of spheres (16 in the papers).
    resolution : int >= 1
        Points per cubemap face edge (16 in Iwasaki et al.: ``6 x 16 x 16`` per sphere).
    r_min, r_max : float
        Innermost and outermost radius, in units of the bounding radius, ``0 < r_min <= r_max``.
    spacing : {"geometric", "uniform"}
        See the module docstring.

    Returns
    -------
    SphereGrid
    """
    vertices = mesh.vertices if hasattr(mesh, "vertices") else mesh[0]
    n_radii = check_int(n_radii, "n_radii", 1)
    resolution = check_int(resolution, "resolution", 1)
    if spacing not in _SPACINGS:
        raise ValueError(f"spacing must be 'geometric' or 'uniform', got {spacing!r}")
    r_min, r_max = float(r_min), float(r_max)
    if not (np.isfinite(r_min) and np.isfinite(r_max) and 0 < r_min <= r_max):
        raise ValueError(f"radii must satisfy 0 < r_min <= r_max (in bounding radii), got r_min={r_min}, r_max={r_max}")
    center, radius = bounding_sphere(vertices)
    if n_radii == 1:
        rel = np.array([r_min])
    elif spacing == "geometric":
        rel = np.geomspace(r_min, r_max, n_radii)
    else:
        rel = np.linspace(r_min, r_max, n_radii)
    return SphereGrid(center, radius, radius * rel, resolution)


def interpolate_field(grid: SphereGrid, values, points, method: str = "numba") -> tuple[np.ndarray, np.ndarray]:
    """Trilinear lookup of a field sampled on ``grid`` at object-space points.

    Parameters
    ----------
    grid : SphereGrid
    values : (n_r, 6, res, res, F...) float
        The field at the grid points (any trailing shape ``F...``).
    points : (..., 3) float
        Object-space query points.
    method : {"numba", "reference"}
        Parallel numba kernel, or the float64 numpy specification.

    Returns
    -------
    field : (..., F...) float64
    beyond : (...) bool
        Points farther than the outermost sphere (their value is that of the
        outermost sphere in their direction).
    """
    if method not in ("numba", "reference"):
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
    values = np.asarray(values, dtype=np.float64)
    if values.shape[:4] != grid.shape:
        raise ValueError(f"values must be {grid.shape} + (F...) to match the grid, got shape {values.shape}")
    points = as_points(points)
    batch, trail = points.shape[:-1], values.shape[4:]
    flat = np.ascontiguousarray(values.reshape(grid.shape + (-1,)))
    if method == "reference":
        corners, weights, beyond = grid.trilinear_corners(points)
        out = np.einsum("qc,qcf->qf", weights, flat.reshape(-1, flat.shape[-1])[corners])
    else:
        rpos, face, s, t, beyond = grid.locate(points)
        out = np.empty((len(rpos), flat.shape[-1]))
        if len(rpos):
            trilinear_kernel(flat, rpos, face, s, t, out)
    return out.reshape(batch + trail), beyond.reshape(batch)
