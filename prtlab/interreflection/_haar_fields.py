"""All-frequency basis radiance fields: ``S_(k,i)`` as sparse Haar cubemaps on the sample spheres (Sec. 4.3).

Iwasaki et al. 2007 (Sec. 4.3) project the basis radiance ``S_(k,i)(p, w)`` of a
source (:mod:`._fields`) "onto spherical harmonics for low-frequency or as a Haar
wavelet for all-frequency". This module is the all-frequency variant: at every
point ``p`` of the source's sample spheres (:class:`prtlab.shadowfields.SphereGrid`,
the grid of its occlusion fields) and for every ``(k, i)``, ``S_(k,i)(p, .)`` is
point-sampled at the texel centres of a cubemap of ``resolution`` texels per face
edge (object space, the conventions of :mod:`prtlab.geometry`), Haar-transformed
(:func:`prtlab.wavelet.haar2d`, orthonormal on texel values) and its ``keep`` largest
coefficients are kept (non-linear approximation, Ng et al. 2003; the selection of
:func:`prtlab.shadowfields.encode_sparse`).

Texel values: the ray ``p + t d_t`` through texel ``t``'s centre hits the source at
``x~``; ``S = h_k(-d_t) Psi_i(x~)`` (barycentric ``Psi_i``, ``h_k`` in the frame of the
interpolated shading normal), 0 on a miss or a back-face hit: exactly the integrand of
:func:`prtlab.interreflection.basis_radiance_at`, sampled instead of projected.
With ``supersample = s > 1`` a texel holds the solid-angle average of ``s x s`` such samples.
Measured on a floor seen from 0.6 above (its edges run along texel rows, the worst case for
point samples), the basis irradiance against 8 x 8 samples per texel: -3.7 % with ``s = 1``,
+1.2 % with ``s = 2`` and 4 (still first order for an edge parallel to the rows), -0.07 % at 8.
The pipeline uses ``s = 1``, as the Haar occlusion fields do.

Storage (:class:`HaarBasisRadianceField`): per sample point and ``(k, i)`` ``keep``
(index, value) pairs, largest ``|value|`` first, unused slots 0 at the end;
indices ``uint16`` (``6 r^2 <= 65536``, i.e. ``r <= 64``; else ``int32``), values
``float32`` (relative rounding ``6e-8``, far below the truncation). That is
``6 keep`` bytes per cubemap: at the defaults (16 x 6 x 16 x 16 points, ``K N = 16``
cubemaps per point, ``keep = 64``) 151 MB per object, against 25 MB for the order-4 SH
field in float64 (the paper's all-frequency Buddha field is 56 MB, Fig. 8). The
squared norm of the dropped coefficients (``energy_lost``, = the squared texel-space
reconstruction error by Parseval) and of the whole cubemap (``energy``) are kept per
cubemap, so the truncation is reported, never hidden: the pass bounds its effect by
Cauchy-Schwarz (:func:`prtlab.interreflection.haar_basis_irradiance`).

Measured figures: ``docs/notes/interreflection.md``.

References
----------
K. Iwasaki et al., EGSR 2007, Sec. 4.3, Eq. (13), Fig. 8.
R. Ng, R. Ramamoorthi, P. Hanrahan, "All-frequency shadows using non-linear wavelet lighting
approximation", SIGGRAPH 2003.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from prtlab._validate import check_int
from prtlab.geometry import RayCaster, cubemap_directions
from prtlab.shadowfields import SphereGrid, encode_sparse

from ._fields import hit_basis_radiance, source_hits

__all__ = ["HaarBasisRadianceField", "haar_basis_radiance_cubemaps", "haar_basis_radiance_field"]

#: Default Haar coefficients kept per (sample point, k, i) cubemap.
DEFAULT_RADIANCE_KEEP = 64
_RAYS_PER_BATCH = 1 << 19


def _check_resolution(res) -> int:
    res = check_int(res, "resolution", 1, meaning="texels per cubemap face edge")
    if res & (res - 1):
        raise ValueError(f"resolution must be a power of two (Haar quadtree), got {res}; use e.g. 16 or 32")
    return res


def _check_source(mesh, basis):
    basis = np.asarray(basis, dtype=np.float64)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if basis.ndim != 2 or basis.shape[1] != len(vertices):
        raise ValueError(f"basis must be (N, n_vertices) = (N, {len(vertices)}), got shape {basis.shape}")
    if not np.all(np.isfinite(basis)):
        raise ValueError("basis contains NaN or inf; pass finite basis functions")
    return basis, vertices


def haar_basis_radiance_cubemaps(mesh, basis, sep, points, resolution: int = 32, supersample: int = 1) -> np.ndarray:
    """Texel cubemaps of the basis radiance ``S_(k,i)(p, .)`` of a source at points (object space).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The source in object space (``vertex_normals`` give its shading side).
    basis : (N, n_vertices) float
        Basis functions ``Psi_i`` at the vertices.
    sep : prtlab.brdf.SeparableBRDF
        The source's separable BRDF (``h_k``).
    points : (..., 3) float
        Object-space points.
    resolution : int
        Texels per cubemap face edge (a power of two).
    supersample : int >= 1
        ``supersample**2`` rays per texel through the texel centres of a ``resolution * supersample``
        cubemap, averaged with their exact solid angles (1: the texel centre only).

    Returns
    -------
    S : (..., K, N, 6, r, r) float64
        ``S_(k,i)`` at the texel centres (:func:`prtlab.geometry.cubemap_directions`), or its
        texel average with ``supersample > 1``.
    """
    basis, vertices = _check_source(mesh, basis)
    res = _check_resolution(resolution)
    ss = check_int(supersample, "supersample", 1, meaning="rays per texel edge")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim == 0 or points.shape[-1] != 3:
        raise ValueError(f"points must be a (..., 3) array, got shape {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError("points contain NaN or inf; pass finite points")
    batch = points.shape[:-1]
    flat = points.reshape(-1, 3)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    n_b, n_k = basis.shape[0], sep.K
    dirs = cubemap_directions(res * ss).reshape(-1, 3)
    n_t = len(dirs)
    out = np.zeros((len(flat), n_k, n_b, n_t))
    if len(flat) == 0 or len(faces) == 0:
        return out.reshape(batch + (n_k, n_b, 6, res, res)) if ss == 1 else np.zeros(batch + (n_k, n_b, 6, res, res))
    normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
    caster = RayCaster([(vertices, faces)])
    step = max(1, _RAYS_PER_BATCH // n_t)
    for a, _, point, direction, hits, at in source_hits(caster, flat, dirs, step):
        out[a + point[at], :, :, direction[at]] = hit_basis_radiance(hits, (at,), dirs[direction[at]], faces,
                                                                     normals, basis, sep)
    if ss > 1:
        from prtlab.geometry import cubemap_solid_angles

        w = cubemap_solid_angles(res * ss).reshape(6, res, ss, res, ss)
        fine = out.reshape(len(flat), n_k, n_b, 6, res, ss, res, ss)
        out = np.einsum("pknfiajb,fiajb->pknfij", fine, w) / w.sum(axis=(2, 4))
    return out.reshape(batch + (n_k, n_b, 6, res, res))


@dataclass
class HaarBasisRadianceField:
    """Sparse Haar cubemaps of the basis radiance ``S_(k,i)`` at a source's sample points (object space).

    Attributes
    ----------
    grid : SphereGrid
    resolution : int
        Cubemap texels per face edge ``r``.
    indices : (n_r, 6, g, g, K, N, keep) uint16 (int32 for r > 64)
        Flat Haar coefficient indices ``f r^2 + i r + j`` (:func:`prtlab.wavelet.haar2d` layout).
    values : (n_r, 6, g, g, K, N, keep) float32
        The coefficients, largest magnitude first, unused slots 0 at the end.
    energy_lost, energy : (n_r, 6, g, g, K, N) float64
        Squared norm of the dropped coefficients and of all of them.
    build_seconds : float
        Wall time of :func:`haar_basis_radiance_field` (0 if unknown).
    """

    grid: SphereGrid
    resolution: int
    indices: np.ndarray
    values: np.ndarray
    energy_lost: np.ndarray
    energy: np.ndarray
    build_seconds: float = 0.0

    @property
    def keep(self) -> int:
        return int(self.indices.shape[-1])

    @property
    def n_terms(self) -> tuple[int, int]:
        """``(K, N)``."""
        return tuple(int(n) for n in self.indices.shape[4:6])

    @property
    def nbytes(self) -> int:
        """Bytes of the stored coefficients (indices and values)."""
        return int(self.indices.nbytes + self.values.nbytes)

    def relative_truncation(self) -> float:
        """``sqrt(sum energy_lost / sum energy)`` over the whole field (0: stored exactly)."""
        total = float(np.sum(self.energy))
        return float(np.sqrt(np.sum(self.energy_lost) / total)) if total > 0 else 0.0

    def truncated(self, n_basis: int) -> HaarBasisRadianceField:
        """The field of the first ``n_basis`` basis functions (no recomputation)."""
        n = slice(0, int(n_basis))
        return HaarBasisRadianceField(self.grid, self.resolution, self.indices[..., n, :], self.values[..., n, :],
                                      self.energy_lost[..., n], self.energy[..., n], self.build_seconds)

    def to_arrays(self) -> dict:
        return {"grid": self.grid.to_arrays(), "resolution": np.int64(self.resolution), "indices": self.indices,
                "values": self.values, "energy_lost": self.energy_lost, "energy": self.energy,
                "build_seconds": np.float64(self.build_seconds)}

    @classmethod
    def from_arrays(cls, d) -> HaarBasisRadianceField:
        res = int(d["resolution"])
        return cls(SphereGrid.from_arrays(d["grid"]), res, np.asarray(d["indices"], _index_dtype(res)),
                   np.asarray(d["values"], np.float32), np.asarray(d["energy_lost"], np.float64),
                   np.asarray(d["energy"], np.float64), float(d.get("build_seconds", 0.0)))


def _index_dtype(res: int):
    return np.uint16 if 6 * res * res <= 1 << 16 else np.int32


def haar_basis_radiance_field(mesh, basis, sep, grid: SphereGrid, resolution: int = 32,
                              keep: int = DEFAULT_RADIANCE_KEEP, supersample: int = 1) -> HaarBasisRadianceField:
    """The all-frequency basis radiance field of a source on its sample spheres (Sec. 4.3).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The source in object space.
    basis : (N, n_vertices) float
        Basis functions ``Psi_i`` at the vertices.
    sep : prtlab.brdf.SeparableBRDF
        The source's separable BRDF (``h_k``).
    grid : SphereGrid
        Its sample spheres (e.g. the grid of its occlusion field).
    resolution : int
        Cubemap texels per face edge (32, as the visibility of ``shadows="haar"``).
    keep : int
        Haar coefficients kept per (sample point, k, i).
    supersample : int >= 1
        Rays per texel edge (:func:`haar_basis_radiance_cubemaps`): texel averages instead of
        texel-centre samples, at ``supersample**2`` times the rays.

    Returns
    -------
    HaarBasisRadianceField

    Notes
    -----
    Cost: ``grid.n_points * 6 r^2 supersample^2`` rays (151 M at the defaults, the same as the Haar
    occlusion field) and one Haar transform per cubemap; storage ``6 keep K N`` bytes per
    sample point.

    Examples
    --------
    >>> from prtlab import brdf
    >>> from prtlab.geometry import builtin_mesh
    >>> from prtlab.shadowfields import sphere_grid
    >>> mesh = builtin_mesh("plane", size=[1.0, 1.0], resolution=[2, 2])
    >>> sep = brdf.separable(brdf.lambert(1.0), 1, resolution=(8, 16))
    >>> field = haar_basis_radiance_field(mesh, np.ones((1, len(mesh.vertices))), sep,
    ...                                   sphere_grid(mesh, n_radii=2, resolution=2), resolution=4, keep=8)
    >>> field.values.shape, field.values.dtype
    ((2, 6, 2, 2, 1, 1, 8), dtype('float32'))
    """
    t0 = time.perf_counter()
    basis, _ = _check_source(mesh, basis)
    res = _check_resolution(resolution)
    keep = check_int(keep, "keep", 1, meaning="Haar coefficients kept per cubemap")
    if not isinstance(grid, SphereGrid):
        raise TypeError(f"grid must be a SphereGrid (prtlab.shadowfields.sphere_grid), got {type(grid).__name__}")
    points = grid.points().reshape(-1, 3)
    n_k, n_b = sep.K, basis.shape[0]
    n_t = 6 * res * res
    shape = grid.shape + (n_k, n_b)
    indices = np.zeros((len(points), n_k, n_b, keep), dtype=_index_dtype(res))
    values = np.zeros((len(points), n_k, n_b, keep), dtype=np.float32)
    lost = np.zeros((len(points), n_k, n_b))
    energy = np.zeros((len(points), n_k, n_b))
    ss = check_int(supersample, "supersample", 1, meaning="rays per texel edge")
    step = max(1, (1 << 22) // (n_t * ss * ss * n_k * n_b))  # bounded memory for the dense cubemaps
    for a in range(0, len(points), step):
        b = min(len(points), a + step)
        cubes = haar_basis_radiance_cubemaps(mesh, basis, sep, points[a:b], res, ss)
        sparse = encode_sparse(cubes, keep)
        indices[a:b] = sparse.indices
        values[a:b] = sparse.values
        lost[a:b] = sparse.energy_lost
        energy[a:b] = np.einsum("pknt,pknt->pkn", cubes.reshape(b - a, n_k, n_b, n_t),
                                cubes.reshape(b - a, n_k, n_b, n_t))
    return HaarBasisRadianceField(grid, res, indices.reshape(shape + (keep,)), values.reshape(shape + (keep,)),
                                  lost.reshape(shape), energy.reshape(shape), time.perf_counter() - t0)
