"""PCA basis functions of an object's surface intensity (Iwasaki et al. 2007, Sec. 4.2).

The object (in object space) is lit by ``N_light`` unit point lights, one at a
time; the reflected diffuse radiance at every vertex, with self-shadowing, is
one column ``B_eta`` of an ``(N_v x N_light)`` matrix. The PCA basis is the
mean ``B_0`` and the first ``N - 1`` left singular vectors of
``C = [B_1 - B_0, ..., B_{N_light} - B_0]``.

Light placement
    *Objects*: ``n_lights`` Fibonacci-sphere directions around the centre of
    the bounding box, at distance ``light_distance`` (default twice the
    bounding radius ``R = max_j |x_j - c|``). The paper puts the lights *on* the
    bounding sphere; there a light touches the extreme vertex and ``1/r^2``
    is unbounded, so the default backs off to ``2 R`` (pass ``light_distance=R``
    for the paper's literal placement).
    *Planes* (``plane=True``, the paper's floor): a regular
    ``ceil(sqrt(n)) x ...`` grid (first ``n_lights`` points) over the plane's
    extent in its tangent axes, at height ``light_distance`` (default half the
    larger extent) along the mean vertex normal.

Reflected radiance
    A Lambertian vertex with albedo ``rho`` and normal ``n`` lit by a unit
    point light at ``y``:

    .. math::

        B_\\eta(x_j) = \\frac{\\rho}{\\pi} \\frac{\\max(0, n_j \\cdot \\omega)}{|y - x_j|^2} V(x_j, y),
        \\qquad \\omega = \\frac{y - x_j}{|y - x_j|},

    on the side the vertex normal points to (``docs/DECISIONS.md``); ``V`` is an
    any-hit shadow ray against the object itself (``RayCaster.occluded`` from the
    offset origin, ``tmax = |y - o'| - epsilon``).

Sign convention
    Each principal component is flipped so that its entry of largest magnitude
    is positive (SVD signs are otherwise arbitrary), so fits are reproducible.

Equal singular values at the cut
    When the last singular value kept equals the first one left out (within
    :data:`EQUAL_SINGULAR` of the largest), their singular vectors span one
    subspace in which no vector is preferred, and the SVD's rounding picks the
    kept one: a square floor under the square grid of lights has such pairs, and
    the vector kept changed with the number of BLAS threads, moving the light the
    floor reflects onto objects by up to 2 %. The whole run of equal values is
    left out instead (:func:`untied_count`): fewer functions than asked for, the
    same on every machine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from prtlab._validate import check_int
from ..geometry import RayCaster, fibonacci_sphere, offset_origins
from ._weights import WeightSolver, _as_samples, reconstruct

__all__ = ["PCABasis", "fit_pca_basis", "point_light_intensity", "pca_light_positions"]

_METHODS = ("fast", "reference")

#: Shadow rays per RayCaster call when rendering the training lights (bounds memory).
_SHADOW_RAYS_PER_CHUNK = 1 << 21

#: Two singular values are equal when they differ by at most this fraction of the largest: far above the SVD's
#: rounding (about ``1e-15`` of it), so the singular vectors of values further apart turn by at most about
#: ``1e-7`` under rounding, below the int16 storage of the basis radiance fields.
EQUAL_SINGULAR = 1e-8


def untied_count(singular_values, n_comps: int) -> int:
    """The largest ``k <= n_comps`` such that singular value ``k - 1`` (0-based) is not equal (within
    :data:`EQUAL_SINGULAR` of the largest) to singular value ``k``: the first ``k`` singular vectors then span a
    subspace that rounding does not choose. ``n_comps`` itself when no value is left out."""
    s = np.asarray(singular_values, dtype=np.float64)
    k = int(n_comps)
    while 0 < k < len(s) and s[k - 1] - s[k] <= EQUAL_SINGULAR * s[0]:
        k -= 1
    return k


@numba.njit(cache=True, parallel=True)
def _point_light_kernel(points, normals, lights, visible, albedo, out):
    """out[l, j] = albedo/pi * max(0, n_j . w) / r^2 * visible[l, j] for every light l, vertex j."""
    n_lights = lights.shape[0]
    n_points = points.shape[0]
    for l in numba.prange(n_lights):
        for j in range(n_points):
            if not visible[l, j]:
                out[l, j] = 0.0
                continue
            dx = lights[l, 0] - points[j, 0]
            dy = lights[l, 1] - points[j, 1]
            dz = lights[l, 2] - points[j, 2]
            r2 = dx * dx + dy * dy + dz * dz
            cos = (normals[j, 0] * dx + normals[j, 1] * dy + normals[j, 2] * dz) / np.sqrt(r2)
            out[l, j] = albedo / np.pi * cos / r2 if cos > 0.0 else 0.0


def _point_light_reference(points, normals, lights, visible, albedo):
    d = lights[:, None, :] - points[None, :, :]
    r2 = np.sum(d * d, axis=-1)
    cos = np.sum(normals[None] * d, axis=-1) / np.sqrt(r2)
    return np.where(visible & (cos > 0), albedo / np.pi * np.maximum(cos, 0.0) / r2, 0.0)


def _as_mesh(mesh_or_object):
    mesh = getattr(mesh_or_object, "mesh", mesh_or_object)
    if not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")):
        raise TypeError(
            "mesh_or_object must be a trimesh.Trimesh or a SceneObject (with .mesh), "
            f"got {type(mesh_or_object).__name__}"
        )
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise ValueError("mesh_or_object has no faces; the PCA basis needs a surface")
    return mesh


def _positive(value, name) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}") from None
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def pca_light_positions(mesh, n_lights: int = 256, light_distance=None, *, plane: bool = False) -> np.ndarray:
    """Point-light positions used to fit a PCA basis (object space).

    Parameters
    ----------
    mesh : trimesh.Trimesh
    n_lights : int >= 1
    light_distance : float, optional
        Distance from the centre (objects) or height above the plane (planes);
        defaults in the module docstring.
    plane : bool
        Lights on a grid above a plane instead of on a sphere.

    Returns
    -------
    positions : (n_lights, 3) float64
    """
    mesh = _as_mesh(mesh)
    n = check_int(n_lights, "n_lights", 1)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = 0.5 * (lo + hi)
    if not plane:
        radius = float(np.max(np.linalg.norm(v - centre, axis=1)))
        dist = 2.0 * radius if light_distance is None else _positive(light_distance, "light_distance")
        return centre + dist * fibonacci_sphere(n)
    normal = np.asarray(mesh.vertex_normals, dtype=np.float64).mean(axis=0)
    norm = np.linalg.norm(normal)
    if not norm > 0:
        raise ValueError("plane=True needs a mesh whose vertex normals agree on a side; got normals summing to 0")
    normal /= norm
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    t1 = np.cross(normal, helper)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(normal, t1)
    a, b = (v - centre) @ t1, (v - centre) @ t2
    extent = max(a.max() - a.min(), b.max() - b.min())
    height = 0.5 * extent if light_distance is None else _positive(light_distance, "light_distance")
    nx = int(np.ceil(np.sqrt(n)))
    ny = int(np.ceil(n / nx))
    ga = a.min() + (np.arange(nx) + 0.5) / nx * (a.max() - a.min())
    gb = b.min() + (np.arange(ny) + 0.5) / ny * (b.max() - b.min())
    pa, pb = np.meshgrid(ga, gb, indexing="ij")
    pts = centre + pa.ravel()[:, None] * t1 + pb.ravel()[:, None] * t2 + height * normal
    return pts[:n]


def point_light_intensity(mesh, light_positions, *, albedo: float = 1.0, shadows: bool = True,
                          method: str = "fast") -> np.ndarray:
    """Reflected diffuse radiance at every vertex for unit point lights, one light at a time.

    Parameters
    ----------
    mesh : trimesh.Trimesh or SceneObject
        Object-space mesh; shading side and normals are the vertex normals.
    light_positions : (n_lights, 3) float
    albedo : float
        Lambertian albedo ``rho``.
    shadows : bool
        Self-shadowing by shadow rays against the mesh.
    method : {"fast", "reference"}
        numba kernel, or its float64 numpy reference.

    Returns
    -------
    intensity : (n_lights, n_vertices) float64
        ``B_eta(x_j)`` of the module docstring.
    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    mesh = _as_mesh(mesh)
    lights = np.asarray(light_positions, dtype=np.float64)
    if lights.ndim != 2 or lights.shape[1] != 3:
        raise ValueError(f"light_positions must have shape (n_lights, 3), got {lights.shape}")
    if not np.all(np.isfinite(lights)):
        raise ValueError("light_positions contains NaN or inf")
    rho = float(albedo)
    if not (np.isfinite(rho) and rho >= 0):
        raise ValueError(f"albedo must be a finite number >= 0, got {albedo!r}")
    points = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    normals = np.ascontiguousarray(mesh.vertex_normals, dtype=np.float64)
    visible = np.ones((len(lights), len(points)), dtype=bool)
    if shadows and len(lights):
        caster = RayCaster([mesh])
        eps = caster.epsilon
        step = max(1, _SHADOW_RAYS_PER_CHUNK // len(points))
        for s in range(0, len(lights), step):  # bounded memory; rays only where the light is in front
            d = lights[s : s + step, None, :] - points[None, :, :]
            facing = np.sum(normals[None] * d, axis=-1) > 0
            li, vi = np.nonzero(facing)
            o = offset_origins(points[vi], normals[vi], d[li, vi], eps)
            dd = lights[s + li] - o
            r = np.linalg.norm(dd, axis=-1)
            blocked = caster.occluded(o, dd, tmax=np.maximum(r - eps, 0.0))
            visible[s + li[blocked], vi[blocked]] = False
    if method == "reference":
        return _point_light_reference(points, normals, lights, visible, rho)
    out = np.empty((len(lights), len(points)))
    _point_light_kernel(points, normals, np.ascontiguousarray(lights), np.ascontiguousarray(visible), rho, out)
    return out


@dataclass(frozen=True, eq=False)
class PCABasis:
    """PCA basis functions ``Psi_i(x_j)`` of one object (Iwasaki et al. 2007, Sec. 4.2).

    Attributes
    ----------
    basis : (N, n_vertices) float64
        Row 0 is the mean ``B_0``; rows ``1..N-1`` the unit principal vectors ``u_mu``.
    singular_values : (min(n_vertices, n_lights),) float64
        All singular values ``sigma`` of the centred matrix ``C``, descending.
    energy : (N,) float64
        ``energy[k] = sum_{mu <= k} sigma_mu^2 / sum sigma^2``: fraction of the centred
        training variance captured by the mean and the first ``k`` components (``energy[0] = 0``).
    samples : (n_samples,) int
        Vertices used for the least-squares weight fit (Sec. 5.2).
    light_positions : (n_lights, 3) float64
        Object-space training lights.
    solver : WeightSolver
        ``A^{-1}`` and the projector at :attr:`samples`.
    """

    basis: np.ndarray
    singular_values: np.ndarray
    energy: np.ndarray
    samples: np.ndarray
    light_positions: np.ndarray
    solver: WeightSolver

    @property
    def n_basis(self) -> int:
        """N, the number of basis functions (mean included)."""
        return self.basis.shape[0]

    @property
    def n_vertices(self) -> int:
        return self.basis.shape[1]

    @property
    def a_inverse(self) -> np.ndarray:
        """(N, N) ``A^{-1}`` of Sec. 5.2 at :attr:`samples`."""
        return self.solver.a_inverse

    @property
    def condition_number(self) -> float:
        """Condition number of ``A`` at :attr:`samples`."""
        return self.solver.condition_number

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays (for the HDF5 cache; no pickle): basis, singular_values, energy, samples, light_positions."""
        return {
            "basis": self.basis,
            "singular_values": self.singular_values,
            "energy": self.energy,
            "samples": self.samples,
            "light_positions": self.light_positions,
        }

    @classmethod
    def from_arrays(cls, arrays) -> "PCABasis":
        """Rebuild from :meth:`to_arrays` output (``A^{-1}`` is recomputed from the basis and samples)."""
        missing = {"basis", "singular_values", "energy", "samples", "light_positions"} - set(arrays)
        if missing:
            raise ValueError(f"arrays lacks {sorted(missing)}; pass the dict written by PCABasis.to_arrays")
        basis = np.asarray(arrays["basis"], dtype=np.float64)
        samples = _as_samples(np.asarray(arrays["samples"]).astype(np.int64), basis.shape[1])
        return cls(basis, np.asarray(arrays["singular_values"], dtype=np.float64),
                   np.asarray(arrays["energy"], dtype=np.float64), samples,
                   np.asarray(arrays["light_positions"], dtype=np.float64), WeightSolver.from_basis(basis, samples))

    def truncated(self, n_basis: int, samples=None) -> "PCABasis":
        """The first ``n_basis`` functions (mean + ``n_basis - 1`` components), samples kept unless given."""
        n = check_int(n_basis, "n_basis", 1)
        if n > self.n_basis:
            raise ValueError(f"n_basis must be <= {self.n_basis} (the fitted basis), got {n}")
        s = self.samples if samples is None else _as_samples(samples, self.n_vertices)
        b = self.basis[:n]
        return PCABasis(b, self.singular_values, self.energy[:n], s, self.light_positions,
                        WeightSolver.from_basis(b, s))

    def weights(self, intensity, *, colour: bool | None = None, method: str = "fast") -> np.ndarray:
        """Least-squares weights ``(..., N[, C])`` of intensity distributions (Sec. 5.2, Eq. 14).

        Parameters
        ----------
        intensity : (..., n_samples[, C]) or (..., n_vertices[, C]) float
            At the sample vertices (in the order of :attr:`samples`) or at every
            vertex (the samples are then picked out). When ``n_samples ==
            n_vertices`` both read the same.
        colour : bool, optional
            Whether there is a trailing colour axis (inferred if omitted).
        method : {"fast", "reference"}
            ``w = P L`` with the precomputed projector, or ``A^{-1} (Psi L)`` per distribution.

        Returns
        -------
        weights : (..., N) or (..., N, C) float64
        """
        v = np.asarray(intensity)
        ns, nv = self.solver.n_samples, self.n_vertices
        if ns != nv and v.ndim >= 1:
            if colour is not True and v.shape[-1] == nv:
                v = v[..., self.samples]
            elif colour is not False and v.ndim >= 2 and v.shape[-2] == nv and v.shape[-1] != ns:
                v = v[..., self.samples, :]
        return self.solver.solve(v, colour=colour, method=method)

    def reconstruct(self, weights, *, colour: bool | None = None) -> np.ndarray:
        """Per-vertex intensity ``(..., n_vertices[, C])`` of weights ``(..., N[, C])``."""
        return reconstruct(self.basis, weights, colour=colour)

    def approximate(self, intensity, *, colour: bool | None = None) -> np.ndarray:
        """``reconstruct(weights(intensity))``: the least-squares approximation at every vertex."""
        return self.reconstruct(self.weights(intensity, colour=colour), colour=colour)


def principal_basis(training, n: int, rank_tol: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and ``n - 1`` principal vectors of the columns of ``training (N_v, N_light)``.

    Returns ``basis (n', N_v)`` (row 0 the mean, then the unit principal vectors, each with its
    largest-magnitude entry positive), all singular values of the centred matrix, and ``energy (n',)``
    as :attr:`PCABasis.energy`. ``n' <= n``: with ``rank_tol`` only the vectors whose singular value
    exceeds ``rank_tol`` times the largest are kept (a rank-deficient training set gives fewer
    functions), and a run of equal singular values at the cut is left out whole (:func:`untied_count`).
    """
    mean = training.mean(axis=1)
    u, s, _ = np.linalg.svd(training - mean[:, None], full_matrices=False)
    n_comps = min(n - 1, len(s))
    if rank_tol is not None:
        n_comps = min(n_comps, int(np.sum(s > rank_tol * max(float(s[0]) if len(s) else 0.0, 1e-300))))
    n_comps = untied_count(s, n_comps)
    comps = u[:, :n_comps].T.copy()
    flip = np.sign(comps[np.arange(n_comps), np.argmax(np.abs(comps), axis=1)])
    comps *= np.where(flip == 0, 1.0, flip)[:, None]
    basis = np.concatenate([mean[None], comps], axis=0)
    total = float(np.sum(s * s))
    energy = np.concatenate([[0.0], np.cumsum(s[:n_comps] ** 2)]) / (total if total > 0 else 1.0)
    return basis, s, energy


def fit_pca_basis(
    mesh_or_object,
    n_basis: int = 16,
    n_lights: int = 256,
    light_distance: float | None = None,
    albedo: float = 1.0,
    seed: int = 0,
    plane: bool = False,
    *,
    n_samples: int | None = None,
    shadows: bool = True,
) -> PCABasis:
    """Fit the PCA basis of an object from ``n_lights`` point lights (Iwasaki et al. 2007, Sec. 4.2).

    Parameters
    ----------
    mesh_or_object : trimesh.Trimesh or SceneObject
        The object in object space (a SceneObject's transform is ignored).
    n_basis : int >= 1
        ``N``: the mean plus ``N - 1`` principal components (paper: 16); fewer when the cut would fall
        between equal singular values (module docstring).
    n_lights : int >= 1
        ``N_light`` training point lights (paper: 256); ``N - 1 <= min(n_lights, n_vertices)``.
    light_distance : float, optional
        Distance of the lights from the centre (or height above a plane); see the module docstring.
    albedo : float
        Lambertian albedo of the training renders (scales the basis only).
    seed : int
        Seed for picking ``n_samples`` sample vertices (unused when all vertices are samples).
    plane : bool
        Lights on a grid above the surface (the paper's floor) instead of a sphere.
    n_samples : int, optional
        Number of sample vertices for the weight fit; default every vertex (Eq. 14).
    shadows : bool
        Self-shadowing of the training renders (default True, as in the paper).

    Returns
    -------
    PCABasis

    Notes
    -----
    With ``B`` the ``(N_v, N_light)`` training matrix and ``B_0`` its row mean,
    ``C = B - B_0 1^T = U S V^T`` and ``Psi_0 = B_0``, ``Psi_mu = u_mu``
    (``mu = 1..N-1``). Every training column lies within
    ``sqrt(sum_{mu >= N} sigma_mu^2)`` (Frobenius, over all columns) of the span.

    References
    ----------
    K. Iwasaki, Y. Dobashi, F. Yoshimoto, T. Nishita. Precomputed radiance
    transfer for dynamic scenes taking into account light interreflection.
    EGSR 2007, Sec. 4.2 (basis) and 5.2 (weights).

    Examples
    --------
    >>> from prtlab.geometry import builtin_mesh
    >>> pca = fit_pca_basis(builtin_mesh("icosphere", subdivisions=1), n_basis=4, n_lights=32)
    >>> pca.basis.shape
    (4, 42)
    """
    mesh = _as_mesh(mesh_or_object)
    n = check_int(n_basis, "n_basis", 1)
    m = check_int(n_lights, "n_lights", 1)
    nv = len(mesh.vertices)
    if n - 1 > min(m, nv):
        raise ValueError(
            f"n_basis = {n} needs n_basis - 1 <= min(n_lights, n_vertices) = {min(m, nv)}; "
            "use more lights or fewer basis functions"
        )
    check_int(seed, "seed")
    lights = pca_light_positions(mesh, m, light_distance, plane=plane)
    training = point_light_intensity(mesh, lights, albedo=albedo, shadows=shadows).T  # (N_v, N_light)
    basis, s, energy = principal_basis(training, n)
    if n_samples is None:
        samples = np.arange(nv)
    else:
        k = check_int(n_samples, "n_samples", n)
        if k > nv:
            raise ValueError(f"n_samples must be <= n_vertices = {nv}, got {k}")
        samples = np.sort(np.random.default_rng(seed).choice(nv, size=k, replace=False))
    return PCABasis(basis, s, energy, samples, lights, WeightSolver.from_basis(basis, samples))
