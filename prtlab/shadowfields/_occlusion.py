"""Object occlusion fields (OOF) and per-vertex self-visibility, in SH (Zhou et al. 2005, Sec. 3-4).

The occlusion field of an object stores, at every point ``p`` of its sample
spheres (:mod:`._grid`), the SH projection of the object's visibility seen
from ``p``::

    O_i(p) = int_S2 V(p, w) Y_i(w) dw,   V(p, w) = 0 if the ray p + t w (t > 0) hits the object, else 1

in the object's own frame. At run time it is looked up (trilinear) at a
receiver point, in the object's frame, and turned to the world frame by SH
rotation (:func:`prtlab.sh.rotate`) when the object is rotated:
``V_world(w) = V_obj(R^T w)``. Uniform scale leaves visibility unchanged once
the point is mapped to object space. Points beyond the outermost sphere are
unoccluded (``O = sqrt(4 pi) Y_00``, the SH of the constant 1).

Projection
    ``V`` is sampled by any-hit rays over a Gauss-Legendre x uniform-azimuth
    product rule (:func:`prtlab.sh.quadrature` with ``degree``; default 47:
    24 x 48 = 1152 rays per point) and projected with its weights. The rule is
    exact for band-limited functions up to that degree; for the step function
    ``V`` its error is that of integrating a discontinuity, about one ring of
    the rule (measured in the tests: the projected cap of a sphere blocker
    against its closed form, :func:`prtlab.sh.blocker_zh`).

Log fields (:func:`log_occlusion_field`): the SH log of every sample, for visibility products taken as the
exponential of a sum (Ren et al. 2006), looked up the same way.

Self-visibility ``V_self(x_j, w)`` of a vertex is the same projection from
the vertex (the ray origin offset off the surface on the side of the ray,
:mod:`prtlab.geometry._raycast`), against its own object only.

Measured figures: ``docs/notes/shadowfields.md``.

References
----------
K. Zhou, Y. Hu, S. Lin, B. Guo, H.-Y. Shum, "Precomputed shadow fields for
dynamic scenes", SIGGRAPH 2005, Sec. 3 (object occlusion fields, sampling on
concentric spheres), Sec. 4 (run-time visibility products).
K. Iwasaki et al., EGSR 2007, Sec. 3.1 and 6 (16 spheres x 6 x 16 x 16 points).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prtlab import sh
from prtlab._validate import as_points, check_int, check_order
from prtlab.geometry import RayCaster

from ._grid import SphereGrid, interpolate_field, sphere_grid
from ._kernels import project_visibility_kernel

__all__ = ["OcclusionField", "occlusion_field", "log_occlusion_field", "self_visibility", "project_visibility",
           "DEFAULT_DEGREE", "LOG_FLOOR"]

#: Default degree of the visibility quadrature (24 x 48 rays per point).
DEFAULT_DEGREE = 47
#: :func:`log_occlusion_field` takes the log of ``LOG_FLOOR + (1 - LOG_FLOOR) V``: a point inside the object (no
#: visible direction) has no log, and the log of a nearly closed visibility grows without bound.
LOG_FLOOR = 1e-2
#: Rays cast per batch (points x directions).
_RAYS_PER_BATCH = 1 << 20
_SQRT4PI = np.sqrt(4.0 * np.pi)


def _check_degree(degree, order: int) -> int:
    if degree is None:
        return max(DEFAULT_DEGREE, 2 * order - 2)
    return check_int(degree, "degree", 2 * order - 2, meaning="at least 2 * order - 2")


def _flat_origins(origins, normals):
    """``origins`` (..., 3) checked and flattened: ``(batch shape, (P, 3), (P, 3) normals or None)``."""
    origins = np.asarray(origins, dtype=np.float64)
    if origins.ndim == 0 or origins.shape[-1] != 3:
        raise ValueError(f"origins must be a (..., 3) array, got shape {origins.shape}")
    if not np.all(np.isfinite(origins)):
        raise ValueError("origins contain NaN or inf; pass finite points")
    nflat = None
    if normals is not None:
        nflat = np.broadcast_to(np.asarray(normals, dtype=np.float64), origins.shape).reshape(-1, 3)
    return origins.shape[:-1], origins.reshape(-1, 3), nflat


def _blocked_batches(caster: RayCaster, flat, nflat, dirs, method: str):
    """Yield ``(a, b, blocked)``: any-hit results ``(b - a, D)`` of the rays from points ``a..b`` toward every
    direction (offset along ``nflat`` when given), at most about ``_RAYS_PER_BATCH`` rays at a time."""
    step = max(1, _RAYS_PER_BATCH // len(dirs))
    for a in range(0, len(flat), step):
        b = min(len(flat), a + step)
        blocked = np.zeros((b - a, len(dirs)), dtype=bool)
        point, direction = np.nonzero(caster.may_hit(flat[a:b], dirs))  # the other rays are unoccluded
        blocked[point, direction] = caster.occluded(flat[a:b][point], dirs[direction], np.inf, method=method,
                                                    normals=None if nflat is None else nflat[a:b][point])
        yield a, b, blocked


def project_visibility(caster: RayCaster, origins, order: int, *, normals=None, degree: int | None = None,
                       method: str = "embree") -> np.ndarray:
    """SH of the visibility seen from points: ``int V(p, w) Y_i(w) dw`` by ray casting.

    Parameters
    ----------
    caster : prtlab.geometry.RayCaster
        The occluding geometry.
    origins : (..., 3) float
        Points.
    order : int
        SH order n.
    normals : (..., 3) float, optional
        Surface normals at the points: each ray then leaves from the surface
        offset on its side (:class:`RayCaster`).
    degree : int, optional
        Degree of the product quadrature (default :data:`DEFAULT_DEGREE`).
    method : {"embree", "numpy"}
        Ray-casting tier of :class:`RayCaster`.

    Returns
    -------
    coeffs : (..., n*n) float64
    """
    order = check_order(order)
    degree = _check_degree(degree, order)
    batch, flat, nflat = _flat_origins(origins, normals)
    dirs, weights = sh.quadrature(order, degree)
    wy = np.ascontiguousarray(weights[:, None] * sh.basis(dirs, order))
    out = np.empty((len(flat), order * order))
    for a, b, blocked in _blocked_batches(caster, flat, nflat, dirs, method):
        project_visibility_kernel(np.ascontiguousarray(blocked), wy, out[a:b])
    return out.reshape(batch + (order * order,))


@dataclass
class OcclusionField:
    """The SH visibility of one object sampled on concentric spheres around it (object space).

    Attributes
    ----------
    grid : SphereGrid
    order : int
    coeffs : (n_r, 6, res, res, order**2) float64
        ``int V(p, w) Y_i(w) dw`` at every grid point ``p``.
    """

    grid: SphereGrid
    order: int
    coeffs: np.ndarray
    #: whether ``coeffs`` are SH logs of the visibility (:func:`log_occlusion_field`): beyond the outermost sphere
    #: the lookup is then 0, the log of the constant 1
    log: bool = False

    def lookup(self, points, transform=None, method: str = "numba") -> np.ndarray:
        """SH visibility of the object seen from world points, in the world frame.

        Parameters
        ----------
        points : (..., 3) float
            World points.
        transform : prtlab.scene.Transform, optional
            The object's pose (default: identity).
        method : {"numba", "reference"}
            Interpolation tier (:func:`interpolate_field`).

        Returns
        -------
        coeffs : (..., order**2) float64
            Beyond the outermost sphere: the constant 1 (unoccluded), or its log 0 for a log field.
        """
        points = as_points(points)
        R = None
        local = points
        if transform is not None:
            R = np.asarray(transform.rotation, dtype=np.float64)
            local = ((points - transform.translate) @ R) / float(transform.scale)
        batch = local.shape[:-1]
        flat = local.reshape(-1, 3)
        gap = flat - self.grid.center
        inside = np.einsum("vi,vi->v", gap, gap) <= self.grid.radii[-1] ** 2  # beyond: exactly unoccluded
        out = np.zeros((len(flat), self.coeffs.shape[-1]))
        out[:, 0] = 0.0 if self.log else _SQRT4PI
        if np.any(inside):
            values, _ = interpolate_field(self.grid, self.coeffs, flat[inside], method=method)
            if R is not None and not np.allclose(R, np.eye(3), rtol=0.0, atol=1e-15):
                values = sh.rotate(values, R, channels=False)
            out[inside] = values
        return out.reshape(batch + out.shape[-1:])

    def to_arrays(self) -> dict:
        return {"grid": self.grid.to_arrays(), "order": np.int64(self.order), "coeffs": self.coeffs,
                **({"log": np.bool_(True)} if self.log else {})}

    @classmethod
    def from_arrays(cls, d) -> "OcclusionField":
        return cls(SphereGrid.from_arrays(d["grid"]), int(d["order"]), np.asarray(d["coeffs"], float),
                   bool(d["log"]) if "log" in d else False)


def log_occlusion_field(field: OcclusionField, floor: float = LOG_FLOOR, tol: float = 1e-6) -> OcclusionField:
    """The SH logarithm of an occlusion field at every sample (Ren et al. 2006, Sec. 4-5): ``g`` with
    ``exp*(g) = floor 1 + (1 - floor) O`` (:func:`prtlab.sh.log`, Newton on a product rule of degree ``8 n - 1``,
    within ``tol`` relative), so that the visibility of several occluders is ``exp*`` of the sum of their logs,
    in any order. ``floor`` keeps every sample the moment vector of a positive function (a sample inside the
    object sees nothing); it lets ``floor`` of an occluded direction through. Slow: 15-35 s a field of 16 x 6 x 16
    x 16 samples at order 4 (one thread)."""
    if field.log:
        raise ValueError("field is already a log field (log_occlusion_field's output); pass the occlusion field")
    if not 0.0 < floor < 1.0:
        raise ValueError(f"floor must lie in (0, 1), got {floor!r}")
    coeffs = field.coeffs.reshape(-1, field.coeffs.shape[-1])
    one = np.zeros(coeffs.shape[-1])
    one[0] = _SQRT4PI
    logs = sh.log((1.0 - floor) * coeffs + floor * one, channels=False, tol=tol, degree=8 * field.order - 1)
    return OcclusionField(field.grid, field.order, logs.reshape(field.coeffs.shape), log=True)


def _mesh_pair(mesh):
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        return np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        return np.asarray(mesh[0], float), np.asarray(mesh[1])
    raise TypeError(f"mesh must be a trimesh.Trimesh or a (vertices, faces) pair, got {type(mesh).__name__}")


def _mesh_and_normals(mesh, normals):
    """``(vertices, faces, normals)`` of ``mesh``; ``normals`` default to ``mesh.vertex_normals``."""
    vertices, faces = _mesh_pair(mesh)
    if normals is None:
        if not hasattr(mesh, "vertex_normals"):
            raise ValueError("normals are required when mesh is a (vertices, faces) pair")
        normals = np.asarray(mesh.vertex_normals, float)
    normals = np.asarray(normals, dtype=np.float64)
    if normals.shape != vertices.shape:
        raise ValueError(f"normals must be {vertices.shape} (one per vertex), got {normals.shape}")
    return vertices, faces, normals


def occlusion_field(mesh, order: int = 4, *, n_radii: int = 16, resolution: int = 16, r_min: float = 0.2,
                    r_max: float = 8.0, spacing: str = "geometric", degree: int | None = None,
                    method: str = "embree") -> OcclusionField:
    """Precompute the object occlusion field of a mesh (Zhou et al. 2005, Sec. 3).

    Parameters
    ----------
    mesh : trimesh.Trimesh or (vertices, faces)
        The object in object space.
    order : int
        SH order n (4 in the papers: 16 coefficients).
    n_radii, resolution, r_min, r_max, spacing
        The sample spheres, see :func:`sphere_grid` (defaults: 16 spheres of
        ``6 x 16 x 16`` points, 0.2..8 bounding radii, geometric).
    degree : int, optional
        Visibility quadrature degree (default :data:`DEFAULT_DEGREE`).
    method : {"embree", "numpy"}
        Ray-casting tier.

    Returns
    -------
    OcclusionField
        SH coefficients ``(n_radii, 6, resolution, resolution, order**2)`` on the grid's points.

    Examples
    --------
    >>> from prtlab.geometry import builtin_mesh
    >>> oof = occlusion_field(builtin_mesh("icosphere", subdivisions=2), 2, n_radii=2, resolution=2)
    >>> oof.coeffs.shape
    (2, 6, 2, 2, 4)
    """
    order = check_order(order)
    vertices, faces = _mesh_pair(mesh)
    grid = sphere_grid((vertices, faces), n_radii, resolution, r_min, r_max, spacing)
    caster = RayCaster([(vertices, faces)])
    coeffs = project_visibility(caster, grid.points(), order, degree=degree, method=method)
    return OcclusionField(grid, order, coeffs)


def self_visibility(mesh, order: int = 4, *, normals=None, degree: int | None = None,
                    method: str = "embree") -> np.ndarray:
    """SH of each vertex's visibility against its own object (object space).

    Parameters
    ----------
    mesh : trimesh.Trimesh or (vertices, faces)
    order : int
    normals : (n_vertices, 3) float, optional
        Vertex normals (default ``mesh.vertex_normals``) for the ray offsets.
    degree : int, optional
    method : {"embree", "numpy"}

    Returns
    -------
    coeffs : (n_vertices, order**2) float64
    """
    order = check_order(order)
    vertices, faces, normals = _mesh_and_normals(mesh, normals)
    caster = RayCaster([(vertices, faces)])
    return project_visibility(caster, vertices, order, normals=normals, degree=degree, method=method)
