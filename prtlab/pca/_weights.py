"""Least-squares weights of a per-vertex basis at sample vertices (Iwasaki et al. 2007, Sec. 5.2).

The intensity ``L`` on an object is approximated by ``sum_i w_i Psi_i(x_j)``.
The weights minimise the squared error at a set of sample vertices ``S``

.. math::

    F(\\mathbf w) = \\sum_{j \\in S} \\Bigl[L(x_j) - \\sum_{i=1}^{N} w_i \\Psi_i(x_j)\\Bigr]^2
    \\quad\\text{(Eq. 14)}, \\qquad
    A \\mathbf w = \\mathbf b, \\quad a_{mn} = \\sum_{j\\in S} \\Psi_m(x_j)\\Psi_n(x_j),
    \\quad b_m = \\sum_{j\\in S} \\Psi_m(x_j) L(x_j).

``A`` depends on the basis only, so ``A^{-1}`` is precomputed; per intensity
distribution the solve is ``w = A^{-1} b``. Folding ``A^{-1}`` into the basis
once gives the *projector* ``P = A^{-1} \\Psi_S`` (``N x |S|``) and ``w = P L_S``:
one matrix product for a whole batch of distributions.

Tiers (``method=``)
    ``"fast"``: ``w = P L_S`` over the flattened batch in one BLAS GEMM (float64);
    a numba loop would only re-implement GEMM, slower. ``"reference"``: the
    paper's two steps written out per distribution, ``b = \\Psi_S L_S`` then
    ``w = A^{-1} b`` (float64, the specification the fast tier is tested against).

Shapes
    ``values``: ``(..., n_samples)`` or, with colour, ``(..., n_samples, C)``.
    The point axis is the last axis when its length is ``n_samples``, else the
    second to last (so a colour axis of length ``n_samples`` would be read as
    the point axis: pass ``colour=True`` to say otherwise). Weights come back as
    ``(..., N)`` or ``(..., N, C)``; :func:`reconstruct` maps them back to
    ``(..., n_vertices[, C])``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prtlab._validate import as_real_array

__all__ = ["WeightSolver", "solve_weights", "reconstruct"]

_METHODS = ("fast", "reference")


def _check_method(method: str) -> str:
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    return method


def _as_basis_matrix(basis, name: str = "basis") -> np.ndarray:
    b = np.asarray(getattr(basis, "basis", basis))
    if b.dtype == object or not (np.issubdtype(b.dtype, np.floating) or np.issubdtype(b.dtype, np.integer)):
        raise TypeError(f"{name} must be a real (N, n_vertices) array or a PCABasis, got dtype {b.dtype}")
    b = b.astype(np.float64, copy=False)
    if b.ndim != 2 or b.shape[0] < 1 or b.shape[1] < 1:
        raise ValueError(
            f"{name} must have shape (N, n_vertices) with N >= 1 basis functions as rows, got shape {b.shape}"
        )
    if not np.all(np.isfinite(b)):
        raise ValueError(f"{name} contains NaN or inf; refit the basis")
    return b


def _as_samples(samples, n_vertices: int) -> np.ndarray:
    if samples is None:
        return np.arange(n_vertices)
    s = np.asarray(samples)
    if s.dtype == bool:
        if s.shape != (n_vertices,):
            raise ValueError(f"samples as a mask must have shape ({n_vertices},), got {s.shape}")
        return np.flatnonzero(s)
    if not np.issubdtype(s.dtype, np.integer):
        raise TypeError(f"samples must be integer vertex indices (or a boolean mask), got dtype {s.dtype}")
    if s.ndim != 1:
        raise ValueError(f"samples must be a 1-D array of vertex indices, got shape {s.shape}")
    if s.size and (s.min() < 0 or s.max() >= n_vertices):
        raise ValueError(f"samples must index vertices in [0, {n_vertices}), got range [{s.min()}, {s.max()}]")
    if np.unique(s).size != s.size:
        raise ValueError("samples must not repeat a vertex; pass each sample vertex once")
    return s.astype(np.intp)


def _point_axis(values: np.ndarray, n_points: int, colour, name: str) -> bool:
    """Whether ``values`` carries a trailing colour axis; validates the point axis."""
    if colour is None:
        if values.ndim >= 1 and values.shape[-1] == n_points:
            return False
        if values.ndim >= 2 and values.shape[-2] == n_points:
            return True
    elif colour:
        if values.ndim >= 2 and values.shape[-2] == n_points:
            return True
    elif values.ndim >= 1 and values.shape[-1] == n_points:
        return False
    raise ValueError(
        f"{name} must have shape (..., {n_points}) or (..., {n_points}, C), got {values.shape}; "
        "the point axis holds one value per sample vertex"
    )


def _as_values(values, name: str) -> np.ndarray:
    return as_real_array(values, name, "every intensity must be finite")


@dataclass(frozen=True, eq=False)
class WeightSolver:
    """Precomputed least-squares solve of Iwasaki et al. 2007, Sec. 5.2.

    Attributes
    ----------
    basis_at_samples : (N, n_samples) float64
        ``Psi_i(x_j)`` at the sample vertices.
    samples : (n_samples,) int
        Vertex indices of the sample points.
    a_matrix : (N, N) float64
        ``A = Psi_S Psi_S^T``.
    a_inverse : (N, N) float64
        ``A^{-1}``.
    projector : (N, n_samples) float64
        ``P = A^{-1} Psi_S``; the weights are ``w = P L_S``.
    condition_number : float
        2-norm condition number of ``A`` (the square of that of ``Psi_S``): the
        relative error of ``w`` is at most about ``condition_number * 2**-52``
        times the relative residual; ``inf`` when the basis is rank-deficient
        at the samples.
    """

    basis_at_samples: np.ndarray
    samples: np.ndarray
    a_matrix: np.ndarray
    a_inverse: np.ndarray
    projector: np.ndarray
    condition_number: float

    @classmethod
    def from_basis(cls, basis, samples=None) -> "WeightSolver":
        """Build the solver of an ``(N, n_vertices)`` basis (or a PCABasis) at ``samples`` (default: all vertices).

        Raises ``ValueError`` when there are fewer samples than basis functions or
        ``A`` is singular (the basis is linearly dependent at the samples).
        """
        b = _as_basis_matrix(basis)
        s = _as_samples(samples, b.shape[1])
        n = b.shape[0]
        if s.size < n:
            raise ValueError(
                f"samples has {s.size} vertices for N = {n} basis functions; give at least N sample vertices"
            )
        psi = np.ascontiguousarray(b[:, s])
        a = psi @ psi.T
        sv = np.linalg.svd(a, compute_uv=False)
        cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
        if not np.isfinite(cond) or cond > 1.0 / np.finfo(np.float64).eps:
            raise ValueError(
                f"A = Psi Psi^T is singular at the sample vertices (condition number {cond:.3g}): the basis "
                "functions are linearly dependent there; use fewer basis functions or more sample vertices"
            )
        a_inv = np.linalg.inv(a)
        a_inv = 0.5 * (a_inv + a_inv.T)
        return cls(psi, s, a, a_inv, a_inv @ psi, cond)

    @property
    def n_basis(self) -> int:
        """N, the basis functions fitted (mean included): the rows of
        :attr:`basis_at_samples`."""
        return self.basis_at_samples.shape[0]

    @property
    def n_samples(self) -> int:
        """The sample vertices, the columns of :attr:`basis_at_samples`."""
        return self.basis_at_samples.shape[1]

    def solve(self, values, *, colour: bool | None = None, method: str = "fast") -> np.ndarray:
        """Weights ``(..., N[, C])`` of intensity distributions given at the sample vertices.

        Parameters
        ----------
        values : (..., n_samples) or (..., n_samples, C) float
            ``L(x_j)`` at the sample vertices, in the order of :attr:`samples`.
        colour : bool, optional
            Whether ``values`` has a trailing colour axis (inferred from the shape if omitted).
        method : {"fast", "reference"}
            See the module docstring.

        Returns
        -------
        weights : (..., N) or (..., N, C) float64
        """
        _check_method(method)
        v = _as_values(values, "values")
        has_colour = _point_axis(v, self.n_samples, colour, "values")
        if method == "fast":
            if not has_colour:  # (..., S) @ (S, N): one GEMM, no copies
                return v @ self.projector.T
            return np.matmul(self.projector, v)  # (N, S) @ (..., S, C), batched GEMM
        if not has_colour:
            v = v[..., None]
        batch = v.shape[:-2]
        c = v.shape[-1]
        flat = v.reshape((-1, self.n_samples, c))
        w = np.empty((flat.shape[0], self.n_basis, c))
        for k in range(flat.shape[0]):
            for ch in range(c):
                b = self.basis_at_samples @ flat[k, :, ch]  # b_m = sum_j Psi_m(x_j) L(x_j)
                w[k, :, ch] = self.a_inverse @ b  # w = A^{-1} b
        w = w.reshape(batch + (self.n_basis, c))
        return w if has_colour else w[..., 0]


def solve_weights(basis, samples, values, *, colour: bool | None = None, method: str = "fast") -> np.ndarray:
    """Least-squares weights of ``basis`` fitting ``values`` at the ``samples`` (Sec. 5.2, Eq. 14).

    Parameters
    ----------
    basis : (N, n_vertices) float or PCABasis
        Basis functions as rows, one value per vertex.
    samples : (n_samples,) int, (n_vertices,) bool, or None
        Sample vertices (``None``: every vertex, as in Eq. 14).
    values : (..., n_samples) or (..., n_samples, C) float
        Intensity at the sample vertices.
    colour : bool, optional
        Whether ``values`` has a trailing colour axis (inferred if omitted).
    method : {"fast", "reference"}

    Returns
    -------
    weights : (..., N) or (..., N, C) float64

    Notes
    -----
    Builds ``A^{-1}`` on every call; keep a :class:`WeightSolver` (or use
    :meth:`PCABasis.weights`) to reuse it across calls.

    References
    ----------
    K. Iwasaki, Y. Dobashi, F. Yoshimoto, T. Nishita. Precomputed radiance
    transfer for dynamic scenes taking into account light interreflection.
    EGSR 2007, Sec. 5.2, Eq. (14).

    Examples
    --------
    >>> import numpy as np
    >>> basis = np.array([[1.0, 1.0, 1.0], [0.0, 1.0, 2.0]])
    >>> solve_weights(basis, None, [1.0, 3.0, 5.0])
    array([1., 2.])
    """
    return WeightSolver.from_basis(basis, samples).solve(values, colour=colour, method=method)


def reconstruct(basis, weights, *, colour: bool | None = None) -> np.ndarray:
    """Per-vertex intensity ``sum_i w_i Psi_i(x_j)`` of weights ``(..., N[, C])``.

    Parameters
    ----------
    basis : (N, n_vertices) float or PCABasis
    weights : (..., N) or (..., N, C) float
    colour : bool, optional
        Whether ``weights`` has a trailing colour axis (inferred if omitted).

    Returns
    -------
    intensity : (..., n_vertices) or (..., n_vertices, C) float64
    """
    b = _as_basis_matrix(basis)
    w = _as_values(weights, "weights")
    has_colour = _point_axis(w, b.shape[0], colour, "weights")
    if not has_colour:
        return w @ b
    return np.swapaxes(np.swapaxes(w, -1, -2) @ b, -1, -2)
