"""All-frequency object occlusion fields and self-visibility: sparse Haar cubemaps (Zhou et al. 2005, Sec. 5).

At every point ``p`` of an object's sample spheres (:class:`SphereGrid`, the
same grid as the SH field) the object's visibility ``V(p, w)`` is rasterised
into a cubemap of ``resolution`` texels per face edge (32 as Zhou et al.;
conventions of :mod:`prtlab.geometry` only): texel ``t`` holds the fraction of
``supersample x supersample`` rays through it that miss the object (one ray
through the texel centre by default). The cubemap is Haar-transformed
(:func:`prtlab.wavelet.haar2d`, orthonormal on texel values) and only the
``keep`` largest coefficients are stored (non-linear approximation, Ng et al.
2003; the same selection as :func:`prtlab.wavelet.keep_largest`), as flat
indices ``f r^2 + i r + j`` (int32) and values (float64) — plain arrays, HDF5
friendly (:meth:`SparseCubemaps.to_arrays`). A vertex's self-visibility is the
same cubemap seen from the vertex against its own object.

Default ``keep = 512`` of the ``6144`` coefficients of a 32-cubemap: the
visibility of a compact object is 1 with a blocked blob, whose Haar expansion
needs about 3 coefficients per node its outline crosses per level. Measured
(non-zero coefficients per sample point, default radii): a sphere mean 70, max
321; the built-in bunny mean 114, 99th percentile 464, max 491 — so 512 store
them exactly. A truncation is reported per point (:attr:`SparseCubemaps.energy_lost`),
never hidden.

Precomputation at the defaults (16 x 6 x 16 x 16 = 24,576 points x 6144 rays =
151 M rays): 32 s for a 1,280-face sphere on 2 idle cores (150 s with the
machine shared four ways); storage 151 MB (int32 index + float64 value per kept
coefficient; ``keep=384`` would still hold the sphere exactly).

Run-time lookup (:meth:`HaarOcclusionField.lookup`)
    A query point is located on the grid exactly as the SH field is
    (:func:`interpolate_field`): fractional sphere index and face coordinates of
    its direction. ``interpolation="trilinear"`` (default) blends the 8 nearest
    samples' coefficient vectors with the trilinear weights (Haar synthesis is
    linear, so this is the blend of the 8 reconstructed cubemaps, texel by
    texel); ``"nearest"`` takes the sample with the largest weight. The blend
    of 8 sharp shadows is a soft, slightly doubled shadow, but anything
    integrated against it (irradiance from a light) is the trilinear
    interpolation of the integrals at the samples, second order in the grid
    spacing where those vary smoothly; nearest is first order (measured in
    the tests against ray casting). Points beyond the outermost sphere see
    ``V = 1``; radii below the innermost are clamped to it. Measured
    (``tests/shadowfields/test_haar_accuracy.py``, slow test): a
    ball of radius 0.5 one unit over 81 floor points, the Fig. 9 light, default
    grid, relative RMS of the irradiance against Monte Carlo: trilinear 0.105,
    nearest 0.222, the cubemap ray cast at the point itself (no field) 0.045,
    and the SH path (order 4) 0.637.

Rotation
    A turned object's visibility is ``V_world(w) = V_obj(R^T w)``: each world
    texel reads the object texel containing ``R^T d_t`` (``d_t`` the world
    texel centre), one texel map per object and frame
    (:func:`rotation_texel_map`). Exact for the 24 rotations that permute the
    cube's texels; otherwise a nearest-texel resampling (error at most half a
    texel in direction, only at shadow edges).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prtlab._validate import check_int
from prtlab.geometry import RayCaster, cubemap_directions, direction_to_cubemap
from prtlab.wavelet import haar2d, ihaar2d

from ._grid import SphereGrid, sphere_grid
from ._occlusion import _blocked_batches, _flat_origins, _mesh_and_normals, _mesh_pair

__all__ = [
    "DEFAULT_HAAR_RESOLUTION",
    "DEFAULT_KEEP",
    "HaarOcclusionField",
    "SparseCubemaps",
    "cubemap_frames",
    "encode_sparse",
    "haar_occlusion_field",
    "haar_self_visibility",
    "rotation_texel_map",
    "visibility_cubemaps",
]

#: Texels per cubemap face edge of the visibility (Zhou et al. 2005: 6 x 32 x 32).
DEFAULT_HAAR_RESOLUTION = 32
#: Haar coefficients kept per visibility cubemap.
DEFAULT_KEEP = 512


def _check_resolution(res) -> int:
    res = check_int(res, "resolution", 1, meaning="texels per cubemap face edge")
    if res & (res - 1):
        raise ValueError(f"resolution must be a power of two (Haar quadtree), got {res}; use e.g. 16 or 32")
    return res


def cubemap_frames() -> np.ndarray:
    """(6, 3, 3) per face: the face axis ``A`` and the directions ``S``, ``T`` of growing ``s``, ``t``.

    A face direction is ``A + sc S + tc T`` with ``sc = 2 s - 1``, ``tc = 2 t - 1``,
    read off :func:`prtlab.geometry.cubemap_directions` (the one place of the convention).
    """
    d = cubemap_directions(2, normalize=False)  # texel centres at sc, tc = +-0.5
    axis = 0.5 * (d[:, 0, 0] + d[:, 1, 1])
    s_ax = d[:, 0, 1] - d[:, 0, 0]
    t_ax = d[:, 1, 0] - d[:, 0, 0]
    return np.ascontiguousarray(np.stack([axis, s_ax, t_ax], axis=1))


def rotation_texel_map(R, resolution: int) -> np.ndarray:
    """World texel -> texel of a frame turned by ``R``: the object texel containing ``R^T d_t``.

    Parameters
    ----------
    R : (3, 3) float
        Rotation of the object (object -> world).
    resolution : int

    Returns
    -------
    texel_map : (6 r^2,) int64
        ``V_world[t] = V_obj[texel_map[t]]``.
    """
    res = _check_resolution(resolution)
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"R must be a finite (3, 3) rotation matrix, got shape {R.shape}")
    d = cubemap_directions(res).reshape(-1, 3)
    if np.allclose(R, np.eye(3), rtol=0.0, atol=1e-15):
        return np.arange(len(d), dtype=np.int64)
    face, _, _, i, j = direction_to_cubemap(d @ R, res)
    return (face * res * res + i * res + j).astype(np.int64)


@dataclass
class SparseCubemaps:
    """A batch of cubemaps stored as their ``keep`` largest Haar coefficients.

    Attributes
    ----------
    resolution : int
        Texels per face edge ``r`` (a power of two).
    indices : (..., keep) int32
        Flat coefficient indices ``f r^2 + i r + j`` in the :func:`prtlab.wavelet.haar2d` layout.
    values : (..., keep) float64
        The coefficients, largest magnitude first (zeros last, where fewer are non-zero).
    energy_lost : (...) float64
        ``sum`` of the squared dropped coefficients (``= sum`` over texels of the
        squared reconstruction error, by Parseval): 0 where the storage is exact.
    """

    resolution: int
    indices: np.ndarray
    values: np.ndarray
    energy_lost: np.ndarray

    @property
    def shape(self) -> tuple:
        return self.indices.shape[:-1]

    @property
    def keep(self) -> int:
        return int(self.indices.shape[-1])

    def coefficients(self) -> np.ndarray:
        """(..., 6, r, r) dense Haar coefficients."""
        r = self.resolution
        flat = self.indices.reshape(-1, self.keep)
        out = np.zeros((len(flat), 6 * r * r))
        rows = np.arange(len(flat))[:, None]
        np.add.at(out, (rows, flat.astype(np.int64)), self.values.reshape(-1, self.keep))  # padding adds 0
        return out.reshape(self.shape + (6, r, r))

    def dense(self, method: str = "numba") -> np.ndarray:
        """(..., 6, r, r) texel values (:func:`prtlab.wavelet.ihaar2d`)."""
        return ihaar2d(self.coefficients(), method=method)

    def to_arrays(self) -> dict:
        return {"resolution": np.int64(self.resolution), "indices": self.indices, "values": self.values,
                "energy_lost": self.energy_lost}

    @classmethod
    def from_arrays(cls, d) -> SparseCubemaps:
        return cls(int(d["resolution"]), np.asarray(d["indices"], np.int32), np.asarray(d["values"], np.float64),
                   np.asarray(d["energy_lost"], np.float64))


def encode_sparse(cubemaps, keep: int = DEFAULT_KEEP) -> SparseCubemaps:
    """Haar-transform cubemaps and keep the ``keep`` largest coefficients of each.

    Parameters
    ----------
    cubemaps : (..., 6, r, r) float
        Texel values, ``r`` a power of two.
    keep : int >= 1
        Coefficients kept per cubemap (all ``6 r^2`` if larger).

    Returns
    -------
    SparseCubemaps
        Coefficients in order of decreasing magnitude within each cubemap, so the
        zero ones (slots not needed) come last and kernels stop at the first zero.
        The kept set is that of :func:`prtlab.wavelet.keep_largest` (largest ``|c|``;
        ties may differ).
    """
    keep = check_int(keep, "keep", 1, meaning="Haar coefficients kept per cubemap")
    cubes = np.asarray(cubemaps, dtype=np.float64)
    if cubes.ndim < 3 or cubes.shape[-3] != 6 or cubes.shape[-1] != cubes.shape[-2]:
        raise ValueError(f"cubemaps must be (..., 6, r, r), got shape {cubes.shape}")
    res = _check_resolution(cubes.shape[-1])
    if not np.all(np.isfinite(cubes)):
        raise ValueError("cubemaps contain NaN or inf; pass finite texel values")
    batch = cubes.shape[:-3]
    n = 6 * res * res
    coeffs = haar2d(cubes).reshape(-1, n)
    k = min(keep, n)
    if k < n:
        part = np.argpartition(-np.abs(coeffs), k - 1, axis=1)[:, :k]
    else:
        part = np.broadcast_to(np.arange(n), coeffs.shape)
    vals = np.take_along_axis(coeffs, part, axis=1)
    order = np.argsort(-np.abs(vals), axis=1, kind="stable")  # largest first: zeros (unused slots) last
    idx = np.take_along_axis(part, order, axis=1)
    vals = np.take_along_axis(vals, order, axis=1)
    lost = np.maximum(np.einsum("bn,bn->b", coeffs, coeffs) - np.einsum("bk,bk->b", vals, vals), 0.0)
    if k < keep:  # pad so every SparseCubemaps of one `keep` has the same width
        idx = np.concatenate([idx, np.zeros((len(idx), keep - k), dtype=idx.dtype)], axis=1)
        vals = np.concatenate([vals, np.zeros((len(vals), keep - k))], axis=1)
    return SparseCubemaps(res, idx.astype(np.int32).reshape(batch + (keep,)), vals.reshape(batch + (keep,)),
                          lost.reshape(batch))


def visibility_cubemaps(caster: RayCaster, origins, resolution: int = DEFAULT_HAAR_RESOLUTION, *, normals=None,
                        supersample: int = 1, method: str = "embree") -> np.ndarray:
    """Visibility cubemaps seen from points, by ray casting: texel = fraction of its rays that escape.

    Parameters
    ----------
    caster : prtlab.geometry.RayCaster
        The occluding geometry.
    origins : (..., 3) float
    resolution : int
        Texels per face edge (power of two).
    normals : (..., 3) float, optional
        Surface normals: each ray leaves from the surface offset on its own side.
    supersample : int >= 1
        ``supersample**2`` rays per texel through the texel centres of a
        ``resolution * supersample`` cubemap, averaged with their exact solid angles.
    method : {"embree", "numpy"}
        Ray-casting tier.

    Returns
    -------
    visibility : (..., 6, r, r) float64 in [0, 1]
    """
    res = _check_resolution(resolution)
    ss = check_int(supersample, "supersample", 1, meaning="rays per texel edge")
    batch, flat, nflat = _flat_origins(origins, normals)
    fine = res * ss
    dirs = cubemap_directions(fine).reshape(-1, 3)
    out = np.empty((len(flat), 6, res, res))
    if ss > 1:
        from prtlab.geometry import cubemap_solid_angles

        w = cubemap_solid_angles(fine).reshape(6, res, ss, res, ss)
        wsum = w.sum(axis=(2, 4))
    for a, b, blocked in _blocked_batches(caster, flat, nflat, dirs, method):
        vis = 1.0 - blocked.reshape(b - a, 6, fine, fine).astype(np.float64)
        if ss > 1:
            vis = (vis.reshape(b - a, 6, res, ss, res, ss) * w).sum(axis=(3, 5)) / wsum
        out[a:b] = vis
    return out.reshape(batch + (6, res, res))


@dataclass
class HaarOcclusionField:
    """Sparse Haar visibility cubemaps of one object at the points of its sample spheres (object space).

    Attributes
    ----------
    grid : SphereGrid
    visibility : SparseCubemaps
        Shape ``(n_r, 6, g, g)`` (the grid's points), ``keep`` coefficients each.
    """

    grid: SphereGrid
    visibility: SparseCubemaps

    @property
    def resolution(self) -> int:
        return self.visibility.resolution

    def corners(self, points, transform=None, interpolation: str = "trilinear") -> tuple[np.ndarray, np.ndarray]:
        """Samples blended at world points: flat sample indices (Q, 8) and weights (Q, 8).

        All weights are 0 for points beyond the outermost sphere (unoccluded).
        """
        if interpolation not in ("trilinear", "nearest"):
            raise ValueError(f"interpolation must be 'trilinear' or 'nearest', got {interpolation!r}")
        points = np.asarray(points, dtype=np.float64)
        if points.ndim == 0 or points.shape[-1] != 3:
            raise ValueError(f"points must be a (..., 3) array, got shape {points.shape}")
        if not np.all(np.isfinite(points)):
            raise ValueError("points contain NaN or inf; pass finite points")
        local = points.reshape(-1, 3)
        if transform is not None:
            R = np.asarray(transform.rotation, dtype=np.float64)
            local = ((local - transform.translate) @ R) / float(transform.scale)
        return _trilinear_corners(self.grid, local, interpolation)

    def lookup(self, points, transform=None, interpolation: str = "trilinear", method: str = "numba") -> np.ndarray:
        """Visibility cubemaps of the object seen from world points, in the world frame.

        Parameters
        ----------
        points : (..., 3) float
            World points.
        transform : prtlab.scene.Transform, optional
            The object's pose (default identity).
        interpolation : {"trilinear", "nearest"}
            See the module docstring.
        method : {"numba", "reference"}
            Haar synthesis tier.

        Returns
        -------
        visibility : (..., 6, r, r) float64
        """
        points = np.asarray(points, dtype=np.float64)
        corners, weights = self.corners(points, transform, interpolation)
        r = self.resolution
        n = 6 * r * r
        coeffs = np.zeros((len(corners), n))
        idx = self.visibility.indices.reshape(-1, self.visibility.keep).astype(np.int64)
        val = self.visibility.values.reshape(-1, self.visibility.keep)
        for c in range(8):
            w = weights[:, c]
            on = w != 0
            rows = np.nonzero(on)[0]
            np.add.at(coeffs, (rows[:, None], idx[corners[on, c]]), w[on, None] * val[corners[on, c]])
        vis = ihaar2d(coeffs.reshape(-1, 6, r, r), method=method).reshape(-1, n)
        vis[np.all(weights == 0, axis=1)] = 1.0
        if transform is not None:
            vis = vis[:, rotation_texel_map(transform.rotation, r)]
        return vis.reshape(points.shape[:-1] + (6, r, r))

    def to_arrays(self) -> dict:
        return {"grid": self.grid.to_arrays(), "visibility": self.visibility.to_arrays()}

    @classmethod
    def from_arrays(cls, d) -> HaarOcclusionField:
        return cls(SphereGrid.from_arrays(d["grid"]), SparseCubemaps.from_arrays(d["visibility"]))


def _trilinear_corners(grid: SphereGrid, local, interpolation: str):
    """The 8 samples and weights of :func:`prtlab.shadowfields.interpolate_field` (same clamping)."""
    corners, weights, beyond = grid.trilinear_corners(local)
    if interpolation == "nearest":
        best = np.argmax(weights, axis=1)
        corners = np.take_along_axis(corners, best[:, None], axis=1).repeat(8, axis=1)
        weights = np.zeros_like(weights)
        weights[:, 0] = 1.0
    weights[beyond] = 0.0
    return corners, weights


def haar_occlusion_field(mesh, *, resolution: int = DEFAULT_HAAR_RESOLUTION, keep: int = DEFAULT_KEEP,
                         n_radii: int = 16, grid_resolution: int = 16, r_min: float = 0.2, r_max: float = 8.0,
                         spacing: str = "geometric", supersample: int = 1,
                         method: str = "embree") -> HaarOcclusionField:
    """Precompute the all-frequency occlusion field of a mesh (Zhou et al. 2005, Sec. 3 and 5).

    Parameters
    ----------
    mesh, method
        The object in object space and the ray-casting tier, as in :func:`prtlab.shadowfields.occlusion_field`.
    resolution : int
        Visibility cubemap texels per face edge (32).
    keep : int
        Haar coefficients kept per sample point (512).
    n_radii, grid_resolution, r_min, r_max, spacing
        The sample spheres (:func:`sphere_grid`; defaults 16 spheres of ``6 x 16 x 16`` points).
    supersample : int
        Rays per texel edge (:func:`visibility_cubemaps`).

    Returns
    -------
    HaarOcclusionField

    Notes
    -----
    Cost: ``n_radii * 6 * grid_resolution**2 * 6 * (resolution * supersample)**2``
    rays (151 M at the defaults); storage ``12 * keep`` bytes per sample point
    (151 MB at the defaults; ``keep=256`` halves it).

    Examples
    --------
    >>> from prtlab.geometry import builtin_mesh
    >>> oof = haar_occlusion_field(builtin_mesh("icosphere", subdivisions=1), resolution=4, keep=16,
    ...                            n_radii=2, grid_resolution=2)
    >>> oof.visibility.indices.shape
    (2, 6, 2, 2, 16)
    """
    vertices, faces = _mesh_pair(mesh)
    grid = sphere_grid((vertices, faces), n_radii, grid_resolution, r_min, r_max, spacing)
    caster = RayCaster([(vertices, faces)])
    res = _check_resolution(resolution)
    keep = check_int(keep, "keep", 1, meaning="Haar coefficients kept per cubemap")
    points = grid.points().reshape(-1, 3)
    chunks = []
    step = max(1, (1 << 22) // (6 * res * res))  # bounded memory for the dense cubemaps
    for a in range(0, len(points), step):
        vis = visibility_cubemaps(caster, points[a : a + step], res, supersample=supersample, method=method)
        chunks.append(encode_sparse(vis, keep))
    sparse = SparseCubemaps(res, np.concatenate([c.indices for c in chunks]).reshape(grid.shape + (keep,)),
                            np.concatenate([c.values for c in chunks]).reshape(grid.shape + (keep,)),
                            np.concatenate([c.energy_lost for c in chunks]).reshape(grid.shape))
    return HaarOcclusionField(grid, sparse)


def haar_self_visibility(mesh, *, resolution: int = DEFAULT_HAAR_RESOLUTION, keep: int = DEFAULT_KEEP,
                         normals=None, points=None, supersample: int = 1, method: str = "embree") -> SparseCubemaps:
    """Sparse Haar cubemap of each vertex's visibility against its own object (object space).

    Parameters
    ----------
    mesh : trimesh.Trimesh or (vertices, faces)
    resolution, keep, supersample
        As in :func:`haar_occlusion_field`.
    normals : (n_vertices, 3) float, optional
        Vertex normals (default ``mesh.vertex_normals``) for the ray offsets.
    points : (n_vertices, 3) float, optional
        Where each vertex is shaded (object space; default the vertices), e.g.
        :func:`prtlab.geometry.shading_points`.
    method : {"embree", "numpy"}

    Returns
    -------
    SparseCubemaps
        Shape ``(n_vertices,)``.
    """
    vertices, faces, normals = _mesh_and_normals(mesh, normals)
    origins = vertices
    if points is not None:
        origins = np.asarray(points, dtype=np.float64)
        if origins.shape != vertices.shape:
            raise ValueError(f"points must be {vertices.shape} (one per vertex), got {origins.shape}")
    res = _check_resolution(resolution)
    keep = check_int(keep, "keep", 1, meaning="Haar coefficients kept per cubemap")
    caster = RayCaster([(vertices, faces)])
    chunks = []
    step = max(1, (1 << 22) // (6 * res * res))
    for a in range(0, len(origins), step):
        vis = visibility_cubemaps(caster, origins[a : a + step], res, normals=normals[a : a + step],
                                  supersample=supersample, method=method)
        chunks.append(encode_sparse(vis, keep))
    if not chunks:
        return SparseCubemaps(res, np.zeros((0, keep), np.int32), np.zeros((0, keep)), np.zeros(0))
    return SparseCubemaps(res, np.concatenate([c.indices for c in chunks]),
                          np.concatenate([c.values for c in chunks]),
                          np.concatenate([c.energy_lost for c in chunks]))
