"""Which basis represents surface intensity best: the journal paper's comparison (Secs. 5-6, Figs. 4-8).

Four bases approximate a per-vertex intensity ``L(x_j)`` with ``N`` terms each:

``"sh"``
    Real spherical harmonics *as functions of the parameter domain*,
    ``Psi_i(u, v) = Y_i(theta = pi v, phi = 2 pi u)`` (``i < N``, the real SH
    of :mod:`prtlab.sh`, polar axis z). The paper expands ``L_k(u, v)`` in ``y(u, v)``
    over the geometry image (Sec. 5.1); it does not say how ``(u, v)`` maps to
    the sphere, so we use the equirectangular map.
``"haar"``
    2D Haar wavelets on ``[0, 1]^2``, the non-standard decomposition (as
    :func:`prtlab.wavelet.haar2d`): the scaling function, then per level
    ``j = 0, 1, ...`` the three wavelets ``psi phi``, ``phi psi``, ``psi psi`` at
    each of the ``4^j`` positions (ordered by type, then position row-major).
    Linear approximation: the first ``N`` in that order (4 terms = piecewise
    constant on 2 x 2 cells, 16 terms = on 4 x 4 cells).
``"fourier"``
    Fourier cosine series ``c_a c_b cos(pi a u) cos(pi b v)`` (``c_0 = 1``,
    ``c_k = sqrt 2``), orthonormal on ``[0, 1]^2``, ordered by
    ``(max(a, b), a + b, a)``: 4 terms = ``a, b < 2``, 9 = ``a, b < 3``, 16 = ``a, b < 4``.
``"pca"``
    The object's PCA basis (:func:`prtlab.pca.fit_pca_basis`): the mean plus ``N - 1`` components.

Weights
    The paper computes the weights of the orthonormal bases by the integral
    ``w_i = int int L(u, v) Psi_i(u, v) du dv`` over the whole square and those
    of PCA by least squares at the vertices (Eq. 6-7). An atlas leaves part of
    the square empty, where ``L`` is undefined, so here *every* basis is fitted by
    the same least squares at the parameterisation vertices (seam vertices once
    per chart), then averaged back to the mesh vertices. For a basis that is
    orthonormal over a fully covered, uniformly sampled domain (the floor) this
    equals the paper's projection up to quadrature error; otherwise it is the
    best any ``N``-term combination of that basis can do at the vertices, so it
    can only favour the orthonormal bases over the paper's procedure.

Error
    ``RMS = sqrt(mean_j (L(x_j) - L~(x_j))^2)`` over the mesh vertices (the
    paper's Fig. 8 measures the RMS of the intensity; its units are not given).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from prtlab._validate import check_int
from ..sh import basis as sh_basis
from ._basis import untied_count
from ._param import SurfaceParam
from ._weights import WeightSolver

__all__ = ["COMPARISON_BASES", "BasisComparison", "uv_basis", "fourier_cosine_indices", "compare_bases",
           "area_light_intensity"]

COMPARISON_BASES = ("sh", "haar", "fourier", "pca")


def _check_uv(uv) -> np.ndarray:
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim < 1 or uv.shape[-1] != 2:
        raise ValueError(f"uv must have shape (..., 2), got {uv.shape}")
    if not np.all(np.isfinite(uv)):
        raise ValueError("uv contains NaN or inf")
    if uv.size and (uv.min() < 0 or uv.max() > 1):
        raise ValueError("uv must lie in [0, 1]^2; rescale the parameterisation")
    return uv


def fourier_cosine_indices(n_terms: int) -> np.ndarray:
    """Frequencies ``(a, b)`` of the first ``n_terms`` Fourier cosine terms, ``(n_terms, 2)`` int."""
    n = check_int(n_terms, "n_terms", 1)
    k = int(np.ceil(np.sqrt(n)))
    a, b = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    a, b = a.ravel(), b.ravel()
    order = np.lexsort((a, a + b, np.maximum(a, b)))
    return np.stack([a[order], b[order]], axis=1)[:n]


def _haar_1d(x, wavelet: bool):
    if not wavelet:
        return np.ones_like(x)
    return np.where(x < 0.5, 1.0, -1.0)


def _haar_functions(uv, n):
    u = np.minimum(uv[..., 0], np.nextafter(1.0, 0.0))
    v = np.minimum(uv[..., 1], np.nextafter(1.0, 0.0))
    out = [np.ones_like(u)]
    level = 0
    while len(out) < n:
        s = 2**level
        su, sv = s * u, s * v
        pu, pv = np.floor(su), np.floor(sv)
        fu, fv = su - pu, sv - pv
        for wu, wv in ((True, False), (False, True), (True, True)):
            val = s * _haar_1d(fu, wu) * _haar_1d(fv, wv)
            for p in range(s):
                for q in range(s):
                    out.append(np.where((pu == p) & (pv == q), val, 0.0))
                    if len(out) == n:
                        return np.stack(out, axis=-1)
        level += 1
    return np.stack(out[:n], axis=-1)


def uv_basis(kind: str, uv, n_terms: int) -> np.ndarray:
    """The first ``n_terms`` functions of a comparison basis at parameter points.

    Parameters
    ----------
    kind : {"sh", "haar", "fourier"}
    uv : (..., 2) float in [0, 1]
    n_terms : int >= 1

    Returns
    -------
    values : (..., n_terms) float64

    Notes
    -----
    ``"haar"`` and ``"fourier"`` are orthonormal on ``[0, 1]^2`` (``du dv``);
    ``"sh"`` is orthonormal for ``2 pi^2 sin(pi v) du dv`` (the sphere's measure).
    Definitions in the module docstring.
    """
    n = check_int(n_terms, "n_terms", 1)
    uv = _check_uv(uv)
    if kind == "fourier":
        ab = fourier_cosine_indices(n)
        cu = np.cos(np.pi * uv[..., 0, None] * ab[:, 0])
        cv = np.cos(np.pi * uv[..., 1, None] * ab[:, 1])
        norm = np.where(ab[:, 0] > 0, np.sqrt(2.0), 1.0) * np.where(ab[:, 1] > 0, np.sqrt(2.0), 1.0)
        return norm * cu * cv
    if kind == "haar":
        return _haar_functions(uv, n)
    if kind == "sh":
        theta, phi = np.pi * uv[..., 1], 2.0 * np.pi * uv[..., 0]
        st = np.sin(theta)
        dirs = np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)
        order = int(np.ceil(np.sqrt(n)))
        return sh_basis(dirs, order)[..., :n]
    raise ValueError(f"kind must be one of ('sh', 'haar', 'fourier'), got {kind!r}; PCA has no (u, v) form")


@dataclass(frozen=True, eq=False)
class BasisComparison:
    """Approximations and RMS errors of one intensity distribution per basis and term count.

    Attributes
    ----------
    intensity : (n_vertices,) float64
        The approximated intensity ``L``.
    bases : tuple of str
    terms : tuple of int
    approximations : dict (basis, n_terms) -> (n_vertices,) float64
    rms : (len(bases), len(terms)) float64
        RMS error over the scored vertices.
    condition : (len(bases), len(terms)) float64
        Condition number of ``A`` of each least-squares fit.
    scored : (n_vertices,) bool
        Vertices the RMS is taken over.
    functions : dict (basis, n_terms) -> int
        Functions each approximation used: ``n_terms``, but for PCA fewer when its cut at ``n_terms`` falls between
        equal singular values (:func:`prtlab.pca.untied_count`).
    """

    intensity: np.ndarray
    bases: tuple
    terms: tuple
    approximations: dict = field(repr=False)
    rms: np.ndarray = field(repr=False)
    condition: np.ndarray = field(repr=False)
    scored: np.ndarray = field(repr=False)
    functions: dict = field(default_factory=dict, repr=False)

    @property
    def relative_rms(self) -> np.ndarray:
        """RMS error divided by the RMS of the intensity over the scored vertices."""
        ref = np.sqrt(np.mean(self.intensity[self.scored] ** 2))
        return self.rms / (ref if ref > 0 else 1.0)

    def table(self, relative: bool = False) -> str:
        """A plain-text table: one row per basis, one column per term count; an entry that used fewer functions
        than its column (:attr:`functions`) gives their number in parentheses."""
        vals = self.relative_rms if relative else self.rms

        def cell(b, n, x):
            used = self.functions.get((b, n), n)
            return f"{x:12.4g}" if used == n else f"{f'{x:.4g} ({used})':>16s}"

        head = "basis   " + "".join(f"{n:>12d}" for n in self.terms)
        rows = [f"{b:<8s}" + "".join(cell(b, n, x) for n, x in zip(self.terms, vals[i]))
                for i, b in enumerate(self.bases)]
        return "\n".join([head, *rows])


def compare_bases(
    intensity,
    param: SurfaceParam,
    pca=None,
    terms=(4, 8, 16),
    bases=COMPARISON_BASES,
    *,
    scored=None,
) -> BasisComparison:
    """Approximate a per-vertex intensity with ``n`` terms of each basis and measure the RMS error.

    Parameters
    ----------
    intensity : (n_vertices,) float
        ``L(x_j)`` at the mesh vertices.
    param : SurfaceParam
        (u, v) parameterisation of the mesh (:func:`prtlab.pca.surface_uv`).
    pca : PCABasis, optional
        Needed when ``"pca"`` is among ``bases``, with the functions each term count takes: ``n`` terms take its
        first ``n``, or fewer when the cut at ``n`` falls between equal singular values (their vectors span one
        subspace and no ``n``-th vector is preferred; :func:`prtlab.pca.untied_count`, the count in
        :attr:`BasisComparison.functions`).
    terms : sequence of int
        Term counts (paper: 4, 8, 16).
    bases : sequence of str
        Any of :data:`COMPARISON_BASES`.
    scored : (n_vertices,) bool, optional
        Vertices the RMS is taken over (default all; e.g. leave out vertices
        lying on another surface, whose intensity is ill-defined).

    Returns
    -------
    BasisComparison

    References
    ----------
    K. Iwasaki, Y. Dobashi, F. Yoshimoto, T. Nishita. (journal version) Sec. 5.1
    (orthonormal bases over a geometry image), 5.2 (PCA), 5.3 and Fig. 8 (RMS).
    """
    L = np.asarray(intensity, dtype=np.float64)
    if not isinstance(param, SurfaceParam):
        raise TypeError(f"param must be a SurfaceParam (from prtlab.pca.surface_uv), got {type(param).__name__}")
    if L.shape != (param.n_vertices,):
        raise ValueError(f"intensity must have shape ({param.n_vertices},) (one value per vertex), got {L.shape}")
    if not np.all(np.isfinite(L)):
        raise ValueError("intensity contains NaN or inf")
    terms = tuple(check_int(n, "n_terms", 1) for n in terms)
    bases = tuple(bases)
    for b in bases:
        if b not in COMPARISON_BASES:
            raise ValueError(f"bases must be drawn from {COMPARISON_BASES}, got {b!r}")
    if "pca" in bases:
        if pca is None:
            raise ValueError("pca is required when 'pca' is among bases: pass fit_pca_basis(mesh)")
        if pca.n_vertices != param.n_vertices:
            raise ValueError(f"pca has {pca.n_vertices} vertices, the mesh {param.n_vertices}; fit it on the same mesh")
        need = max(_pca_functions(pca, n) for n in terms)
        if pca.n_basis < need:
            raise ValueError(f"pca has {pca.n_basis} basis functions, fewer than the {need} that max(terms) = "
                             f"{max(terms)} terms take")
    mask = np.ones(param.n_vertices, bool) if scored is None else np.asarray(scored, dtype=bool)
    if mask.shape != (param.n_vertices,):
        raise ValueError(f"scored must be a boolean mask of shape ({param.n_vertices},), got {mask.shape}")
    approximations, functions = {}, {}
    rms = np.zeros((len(bases), len(terms)))
    cond = np.zeros_like(rms)
    L_param = param.to_param(L)
    for i, b in enumerate(bases):
        for k, n in enumerate(terms):
            m = functions[(b, n)] = _pca_functions(pca, n) if b == "pca" else n
            if b == "pca":
                solver = WeightSolver.from_basis(pca.basis[:m])
                approx = solver.solve(L) @ pca.basis[:m]
            else:
                psi = uv_basis(b, param.uv, n).T  # (n, n_param)
                solver = WeightSolver.from_basis(psi)
                approx = param.to_vertices(solver.solve(L_param) @ psi)
            approximations[(b, n)] = approx
            rms[i, k] = np.sqrt(np.mean((approx - L)[mask] ** 2))
            cond[i, k] = solver.condition_number
    return BasisComparison(L, bases, terms, approximations, rms, cond, mask, functions)


def _pca_functions(pca, n: int) -> int:
    """PCA functions ``n`` terms take: the mean and the components up to the last cut at or before ``n - 1``
    that falls between unequal singular values."""
    return 1 + untied_count(pca.singular_values, n - 1)


def area_light_intensity(meshes, light, receiver: int = 0, *, albedo: float = 1.0, n: int = 16,
                         shadows: bool = True) -> np.ndarray:
    """Direct diffuse radiance at a receiver's vertices from an area light, by a midpoint rule on the light.

    Parameters
    ----------
    meshes : Scene or sequence of trimesh.Trimesh
        Occluders in world space (a Scene uses its objects' transforms).
    light : AreaLight
        ``center + s u + t v``, one-sided toward ``cross(u, v)``, radiance ``L_e`` (scalar or RGB: its mean is used).
    receiver : int
        Index (into the RayCaster's objects) of the object whose vertices are shaded.
    albedo : float
        Lambertian albedo of the receiver.
    n : int
        ``n x n`` midpoint points on the light (deterministic, no noise).
    shadows : bool
        Shadow rays against every object.

    Returns
    -------
    radiance : (n_vertices,) float64

    Notes
    -----
    .. math::

        L(x) = \\frac{\\rho}{\\pi} \\sum_{k=1}^{n^2} L_e
        \\frac{\\max(0, n_x\\cdot\\omega_k)\\, \\max(0, -n_L\\cdot\\omega_k)}{|y_k - x|^2}
        V(x, y_k) \\frac{|A|}{n^2}

    with ``y_k`` the cell centres of the ``n x n`` grid in ``(s, t)`` and
    ``|A| = 4 |u x v|``; the receiver side is its vertex normal's
    (docs/DECISIONS.md). Converges to the reference's direct light (tested
    against :func:`prtlab.reference.direct` within its standard error plus the
    rule's own error estimate ``|I_n - I_{2n}|``).
    """
    from ..geometry import RayCaster

    caster = meshes if isinstance(meshes, RayCaster) else RayCaster(meshes)
    check_int(n, "n", 1)
    if not 0 <= receiver < caster.n_objects:
        raise ValueError(f"receiver must be in [0, {caster.n_objects}), got {receiver}")
    pts = caster.world_vertices(receiver)
    faces = caster.faces(receiver)
    import trimesh

    normals = np.asarray(trimesh.Trimesh(pts, faces, process=False).vertex_normals, dtype=np.float64)
    c, u, v = (np.asarray(a, dtype=np.float64) for a in (light.center, light.u, light.v))
    le = float(np.mean(light.radiance))
    nl = np.cross(u, v)
    area = 4.0 * np.linalg.norm(nl)
    nl /= np.linalg.norm(nl)
    s = -1.0 + (2.0 * np.arange(n) + 1.0) / n
    ss, tt = np.meshgrid(s, s, indexing="ij")
    ys = c + ss.ravel()[:, None] * u + tt.ravel()[:, None] * v  # (n^2, 3)
    total = np.zeros(len(pts))
    from ..geometry import offset_origins

    eps = caster.epsilon
    for y in ys:
        d = y - pts
        r2 = np.sum(d * d, axis=1)
        w = d / np.sqrt(r2)[:, None]
        cx = np.maximum(np.sum(normals * w, axis=1), 0.0)
        cy = np.maximum(-(w @ nl), 0.0)
        contrib = le * cx * cy / r2
        if shadows:
            live = contrib > 0
            o = offset_origins(pts[live], normals[live], w[live], eps)
            dd = y - o
            tmax = np.linalg.norm(dd, axis=1) - eps
            blocked = caster.occluded(o, dd, tmax=tmax)
            contrib[np.flatnonzero(live)[blocked]] = 0.0
        total += contrib
    return albedo / np.pi * total * area / (n * n)
