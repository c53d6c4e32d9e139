"""The per-frame shader passes of the portals pipeline (Yue et al. 2009, Section 5, Appendix)."""

from __future__ import annotations

import weakref
from contextlib import contextmanager

import numba
import numpy as np

from prtlab.wavelet import SparseTransfer, haar2d

from . import _kernels

__all__ = ["direct_pass", "indirect_pass", "glossy_direct_pass", "glossy_lobe_pass", "glossy_indirect_pass"]

_METHODS = ("numba", "reference")

#: multiply-adds below which a pass runs its (parallel) kernel on one thread: a parallel region waits for its
#: slowest thread, which on a shared, busy machine costs a scheduler time slice (``docs/notes/portals.md``); above
#: it the threads pay off.
PARALLEL_MIN_WORK = 1 << 22


@contextmanager
def _threads_for(work: float):
    """Run the numba kernels inside on one thread when ``work`` (multiply-adds) is small."""
    if work >= PARALLEL_MIN_WORK or numba.get_num_threads() == 1:
        yield
        return
    previous = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(previous)


def _check_light_sh(light_sh, shape, against: str) -> np.ndarray:
    light_sh = np.asarray(light_sh, dtype=np.float64)
    if light_sh.shape != shape:
        raise ValueError(f"light_sh must have shape {shape} to match {against}, got {light_sh.shape}")
    if not np.all(np.isfinite(light_sh)):
        raise ValueError("light_sh has NaN or infinite values")
    return light_sh


def _check_method(method):
    if method not in _METHODS:
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")


def direct_pass(direct: SparseTransfer, albedo, shell_cube, method: str = "numba") -> np.ndarray:
    """Direct radiance ``L_d(v) = rho_v sum_k T_k(v) L_s,k`` (Appendix Eq. 7, Section 4.1.2).

    Parameters
    ----------
    direct : SparseTransfer
        8-bit per-vertex transfer, pulse or Haar per vertex (``V`` vertices).
    albedo : (V, 3) float
    shell_cube : (6, r, r, 3) float
        Texel averages of the shell light (:func:`prtlab.portals.shell_light`).
    method : {"numba", "reference"}
        ``"numba"``: one fused kernel (``prange`` over vertices) reading only the
        stored 8-bit entries, the albedo folded in (pulse rows summed in float32:
        :func:`direct_from_light`); ``"reference"``: dense float64
        coefficients (:meth:`prtlab.wavelet.SparseTransfer.dot`).

    Returns
    -------
    (V, 3) float64

    Notes
    -----
    Both bases are orthonormal in texel space, so the dot product in the
    vertex's stored basis equals the texel-space one:
    ``sum_k T_k L_k = sum_j haar(T)_j haar(L)_j``.
    """
    _check_method(method)
    albedo = np.asarray(albedo, dtype=np.float64)
    if albedo.shape != (direct.n_vertices, 3):
        raise ValueError(f"albedo must have shape ({direct.n_vertices}, 3), got {albedo.shape}")
    cube = _check_cube(shell_cube, direct.res)
    if method == "reference":
        return direct.dot(cube, method="reference") * albedo
    return direct_from_light(direct, albedo, shell_coefficients(cube, haar=bool(np.any(direct.basis == direct.HAAR))))


def shell_coefficients(shell_cube, haar: bool = True) -> np.ndarray:
    """The shell light in both bases of the 8-bit transfers, ``(2 T, 3)`` float64 (``T = 6 r^2``): rows ``0..T-1``
    the texels (pulse), rows ``T..2T-1`` the Haar coefficients (:func:`prtlab.wavelet.haar2d`; zeros unless
    ``haar``). Computed once per frame and portal, shared by the direct pass and the surface source."""
    cube = np.asarray(shell_cube, dtype=np.float64)
    n = cube.shape[0] * cube.shape[1] * cube.shape[2]
    light = np.zeros((2 * n, 3))
    light[:n] = cube.reshape(n, 3)
    if haar:
        with _threads_for(0):  # ~0.1 ms of work: a parallel region's start-up would cost more
            light[n:] = haar2d(cube, channels=True).reshape(n, 3)
    return light


#: the texel runs of each SparseTransfer (:func:`texel_runs`), built on first use
_RUNS: "weakref.WeakKeyDictionary[SparseTransfer, tuple]" = weakref.WeakKeyDictionary()


def texel_runs(direct: SparseTransfer) -> tuple:
    """``(run_ptr (V + 1,) int64, run_start (R,) int32, run_len (R,) int32)``: the pulse rows of ``direct`` as runs
    of consecutive texels (a run per maximal stretch of consecutive indices; Haar rows have none), for
    :func:`prtlab.portals._kernels.direct_runs_kernel`. Cached per transfer object."""
    if direct in _RUNS:
        return _RUNS[direct]
    counts = np.diff(direct.indptr)
    row = np.repeat(np.arange(direct.n_vertices), counts)
    raw = direct.indices.astype(np.int64)
    pulse = direct.basis[row] == SparseTransfer.PULSE
    start = np.ones(len(raw), dtype=bool)
    start[1:] = (row[1:] != row[:-1]) | (raw[1:] != raw[:-1] + 1)
    first = np.nonzero(start & pulse)[0]
    ends = np.nonzero(start)[0]
    length = np.diff(np.append(ends, len(raw)))[np.searchsorted(ends, first)]
    run_ptr = np.searchsorted(row[first], np.arange(direct.n_vertices + 1)).astype(np.int64)
    out = (run_ptr, raw[first].astype(np.int32), length.astype(np.int32))
    _RUNS[direct] = out
    return out


def direct_from_light(direct: SparseTransfer, albedo, light) -> np.ndarray:
    """:func:`direct_pass` (numba tier) from the shell light's coefficients ``light`` (:func:`shell_coefficients`,
    ``(2 T, 3)``) and a checked ``(V, 3)`` float64 ``albedo``: pulse rows as texel runs, those the light leaves
    black skipped, summed in float32 (:func:`prtlab.portals._kernels.direct_runs_kernel`: within ``(n + 2) eps_32``
    of a row's sum of absolute terms); Haar rows in float64."""
    out = np.empty((direct.n_vertices, 3))
    if direct.n_vertices:
        operands = direct_operands(direct, albedo, light)
        with _threads_for(3 * len(direct.codes)):
            direct_rows(operands, 0, direct.n_vertices, out)
    return out


def direct_operands(direct: SparseTransfer, albedo, light) -> tuple:
    """The operands of :func:`prtlab.portals._kernels.direct_runs_kernel` for :func:`direct_rows`: the transfer's
    texel runs and the light's layouts (one serial pass over the light)."""
    run_ptr, run_start, run_len = texel_runs(direct)
    light = np.ascontiguousarray(light, dtype=np.float64)
    n = len(light) // 2
    light_t, lit = np.empty((3, 2 * n)), np.empty(n + 1, dtype=np.int32)
    light32_t = np.empty((3, n + 7), np.float32)  # 7 zero columns for the runs' masked lanes
    _kernels.light_layout_kernel(light, light_t, lit, light32_t)
    return (direct.indptr, run_ptr, run_start, run_len, direct.indices, direct.codes, direct.scale, direct.basis,
            np.int64(direct.sign_bit), light_t, lit, light32_t, np.ascontiguousarray(albedo))


def direct_rows(operands: tuple, a: int, b: int, out, part: int = 2) -> None:
    """The direct radiance of vertices ``a .. b - 1`` into ``out[a:b]`` (each vertex's sums on its own: the same
    bits whatever the split of the rows); ``part`` 0 their pulse rows only, 1 their Haar rows only, 2 all."""
    indptr, run_ptr, run_start, run_len, indices, codes, scale, basis, sign_bit, light_t, lit, light32_t, albedo = \
        operands
    _kernels.direct_runs_kernel(indptr[a : b + 1], run_ptr[a : b + 1], run_start, run_len, indices, codes, scale[a:b],
                                basis[a:b], sign_bit, light_t, lit, light32_t, albedo[a:b], out[a:b], np.int64(part))


def indirect_pass(transfer, light_sh, method: str = "numba") -> np.ndarray:
    """Indirect radiance of diffuse vertices ``L_i(v) = sum_lm t_lm(v) c_lm`` (Appendix Eq. 6).

    Parameters
    ----------
    transfer : (V, n*n, 3) float
        Per-vertex transfer vectors per colour channel (albedo folded in).
    light_sh : (n*n, 3) float
        SH coefficients of the shell light (:func:`prtlab.portals.shell_sh`).
    method : {"numba", "reference"}

    Returns
    -------
    (V, 3) float64
    """
    _check_method(method)
    transfer = np.asarray(transfer)
    if transfer.ndim != 3 or transfer.shape[2] != 3:
        raise ValueError(f"transfer must have shape (V, n*n, 3), got {transfer.shape}")
    light_sh = _check_light_sh(light_sh, transfer.shape[1:], "the transfer")
    if method == "reference":
        return np.einsum("vic,ic->vc", transfer.astype(np.float64), light_sh)
    out = np.zeros((transfer.shape[0], 3))
    if transfer.shape[0]:
        with _threads_for(transfer.size):
            _kernels.indirect_pass_kernel(np.ascontiguousarray(transfer, dtype=np.float32),
                                          np.ascontiguousarray(light_sh), out)
    return out


def _check_cube(cube, res):
    cube = np.asarray(cube, dtype=np.float64)
    want = (6, res, res, 3)
    if cube.shape != want:
        raise ValueError(f"shell_cube must have shape {want} to match the transfer (r = {res}), got "
                         f"{cube.shape}; build it with shell_light(source, {res})")
    if not np.all(np.isfinite(cube)):
        raise ValueError("shell_cube has NaN or infinite values")
    return cube


def glossy_direct_pass(glossy: SparseTransfer, rows, weights, ks, shell_cube, method: str = "numba") -> np.ndarray:
    """Specular direct radiance of glossy vertices toward the viewer (Section 4.1.2, Appendix Eq. 7 per ``w_o``).

    ``L_s(v) = ks_v sum_q weights[v, q] sum_k S_{rows[v, q], k} L_s,k``: each glossy vertex stores one 8-bit
    transfer cubemap per discretised outgoing direction ``w_oj`` (rows of ``glossy``,
    :func:`prtlab.portals.glossy_direct_transfer`); the view direction blends the rows around it
    (:func:`prtlab.portals.view_interpolation`).

    Parameters
    ----------
    glossy : SparseTransfer
        ``V_g * J`` rows: vertex ``v``'s direction ``j`` at row ``v J + j``.
    rows : (V_g, Q) int
        Rows blended per vertex.
    weights : (V_g, Q) float
    ks : (V_g, 3) float
        Specular albedo.
    shell_cube : (6, r, r, 3) float
    method : {"numba", "reference"}
        ``"numba"``: a fused ``prange`` kernel over vertices reading the stored entries of the blended rows;
        ``"reference"``: the rows decoded to float64 with numpy, dotted with the light, blended.

    Returns
    -------
    (V_g, 3) float64
    """
    _check_method(method)
    rows = np.asarray(rows)
    weights = np.asarray(weights, dtype=np.float64)
    ks = np.asarray(ks, dtype=np.float64)
    if rows.ndim != 2 or weights.shape != rows.shape or rows.dtype.kind not in "iu":
        raise ValueError(f"rows must be an integer (V_g, Q) array and weights of the same shape, got {rows.shape} "
                         f"and {weights.shape}")
    if rows.size and (rows.min() < 0 or rows.max() >= glossy.n_vertices):
        raise ValueError(f"rows must index the {glossy.n_vertices} rows of the glossy transfer")
    if ks.shape != (rows.shape[0], 3):
        raise ValueError(f"ks must have shape ({rows.shape[0]}, 3), got {ks.shape}")
    cube = _check_cube(shell_cube, glossy.res)
    n = 6 * glossy.res * glossy.res
    light = np.zeros((2 * n, 3))
    light[:n] = cube.reshape(n, 3)
    if np.any(glossy.basis == glossy.HAAR):
        light[n:] = haar2d(cube, channels=True).reshape(n, 3)
    rows = rows.astype(np.int64)
    if method == "reference":
        flat = rows.ravel()
        starts, stops = glossy.indptr[flat], glossy.indptr[flat + 1]
        owner = np.repeat(np.arange(len(flat)), stops - starts)
        entry = np.concatenate([np.arange(a, b) for a, b in zip(starts, stops)]) if len(flat) else np.zeros(0, int)
        raw = glossy.indices[entry].astype(np.int64)
        k = (raw & (glossy.sign_bit - 1)) + n * glossy.basis[flat[owner]].astype(np.int64)
        value = np.where(raw >= glossy.sign_bit, -1.0, 1.0) * glossy.codes[entry] \
            * glossy.scale[flat[owner]].astype(np.float64) / 255.0
        per_row = np.zeros((len(flat), 3))
        np.add.at(per_row, owner, value[:, None] * light[k])
        return (per_row.reshape(rows.shape + (3,)) * weights[..., None]).sum(axis=1) * ks
    out = np.empty((rows.shape[0], 3))
    if rows.shape[0]:
        work = 3 * int((glossy.indptr[rows + 1] - glossy.indptr[rows]).sum())
        with _threads_for(work):
            _kernels.glossy_direct_pass_kernel(glossy.indptr, glossy.indices, glossy.codes, glossy.scale,
                                               glossy.basis, np.int64(glossy.sign_bit), light,
                                               np.ascontiguousarray(rows), np.ascontiguousarray(weights),
                                               np.ascontiguousarray(ks), out)
    return out


def glossy_lobe_pass(indptr, indices, values, res: int, reflected, exponent, ks, shell_cube,
                     method: str = "numba") -> np.ndarray:
    """Specular direct radiance of glossy vertices from their Phong lobe at the shell texels they see
    (``glossy_direct="lobe"``; the paper's per-view cubemaps are :func:`glossy_direct_pass`).

    ``L_s(v) = ks_v (e_v + 2) / 2 sum_k W_vk max(0, w_k . r_v)^e_v L_k``: ``W_vk`` is the vertex's visible
    cosine-weighted solid angle of texel ``k`` over pi (its diffuse direct transfer,
    :func:`prtlab.portals.direct_transfer`, in float32), ``w_k`` the texel's centre direction and ``r_v`` the
    mirror of the view direction about the normal (``max(0, r(w) . w_o) = max(0, w . r(w_o))``). The lobe is taken
    constant over a texel: exact as the texels shrink, and close while the lobe spans several texels (its half
    width ``acos(0.5^(1 / e))``, 21 degrees at ``e = 10`` against a texel of 2.8 degrees at ``res = 32``).

    Parameters
    ----------
    indptr, indices, values : CSR rows, one per glossy vertex (texel index ``face r^2 + i r + j``, weight ``W``)
    res : int
        Face resolution ``r`` of the texels the rows index (and of ``shell_cube``).
    reflected : (V_g, 3) float
        Unit mirror directions of the view directions.
    exponent : (V_g,) float
    ks : (V_g, 3) float
    shell_cube : (6, r, r, 3) float
    method : {"numba", "reference"}
        ``"numba"``: a ``prange`` kernel over vertices; ``"reference"``: numpy float64.

    Returns
    -------
    (V_g, 3) float64
    """
    from prtlab.geometry import cubemap_directions

    _check_method(method)
    indptr = np.asarray(indptr, dtype=np.int64)
    reflected = np.asarray(reflected, dtype=np.float64)
    exponent = np.asarray(exponent, dtype=np.float64)
    ks = np.asarray(ks, dtype=np.float64)
    n_g = len(indptr) - 1
    if reflected.shape != (n_g, 3) or exponent.shape != (n_g,) or ks.shape != (n_g, 3):
        raise ValueError(f"reflected, exponent and ks must have shapes ({n_g}, 3), ({n_g},), ({n_g}, 3): one per "
                         f"row; got {reflected.shape}, {exponent.shape}, {ks.shape}")
    cube = _check_cube(shell_cube, int(res))
    light = np.ascontiguousarray(cube.reshape(-1, 3))
    dirs = cubemap_directions(res).reshape(-1, 3)
    indices = np.asarray(indices)
    if len(indices) and (indices.min() < 0 or indices.max() >= len(dirs)):
        raise ValueError(f"indices must be texels of the {res} x {res} shell cubemap")
    if method == "reference":
        owner = np.repeat(np.arange(n_g), np.diff(indptr))
        c = np.maximum(0.0, np.einsum("pk,pk->p", dirs[indices], reflected[owner]))
        w = np.asarray(values, dtype=np.float64) * c ** exponent[owner]
        out = np.zeros((n_g, 3))
        np.add.at(out, owner, w[:, None] * light[indices])
        return out * (0.5 * (exponent + 2.0))[:, None] * ks
    out = np.empty((n_g, 3))
    if n_g:
        with _threads_for(8 * len(indices)):
            _kernels.glossy_lobe_kernel(indptr, np.ascontiguousarray(indices, dtype=np.int32),
                                        np.ascontiguousarray(values, dtype=np.float32), dirs, reflected,
                                        exponent, ks, light, out)
    return out


def glossy_indirect_pass(matrix, light_sh, view_dirs, method: str = "numba") -> np.ndarray:
    """Indirect radiance of glossy vertices: matrix-vector product, then evaluation at the view (Appendix Eq. 6).

    ``L_i(v, w_o) = sum_j Y_j(w_o) sum_i M_ji(v) c_i``.

    Parameters
    ----------
    matrix : (V_g, n_out^2, n^2, 3) float
        Specular transfer matrices (``ks`` folded in), :func:`prtlab.portals.final_gather` with ``glossy``.
    light_sh : (n^2, 3) float
        SH coefficients of the shell light.
    view_dirs : (V_g, 3) float
        Unit directions toward the viewer.
    method : {"numba", "reference"}
        ``"numba"``: a ``prange`` kernel over vertices; ``"reference"``: numpy ``einsum``.

    Returns
    -------
    (V_g, 3) float64
        Indirect radiance toward ``view_dirs``.
    """
    import prtlab.sh as sh

    _check_method(method)
    matrix = np.asarray(matrix)
    view_dirs = np.asarray(view_dirs, dtype=np.float64)
    if matrix.ndim != 4 or matrix.shape[3] != 3:
        raise ValueError(f"matrix must have shape (V_g, n_out^2, n^2, 3), got {matrix.shape}")
    light_sh = _check_light_sh(light_sh, matrix.shape[2:], "the matrix")
    if view_dirs.shape != (matrix.shape[0], 3) or not np.all(np.isfinite(view_dirs)):
        raise ValueError(f"view_dirs must be a finite ({matrix.shape[0]}, 3) array, got shape {view_dirs.shape}")
    order_out = int(round(np.sqrt(matrix.shape[1])))
    if order_out * order_out != matrix.shape[1]:
        raise ValueError(f"matrix.shape[1] must be a square (n_out^2), got {matrix.shape[1]}")
    if method == "reference":
        y = sh.basis_reference(view_dirs, order_out) if len(view_dirs) else np.zeros((0, matrix.shape[1]))
        return np.einsum("vj,vjic,ic->vc", y, matrix.astype(np.float64), light_sh)
    out = np.empty((matrix.shape[0], 3))
    if matrix.shape[0]:
        with _threads_for(matrix.size):
            y = sh.basis(view_dirs, order_out)
            _kernels.glossy_indirect_pass_kernel(np.ascontiguousarray(matrix, dtype=np.float32),
                                                 np.ascontiguousarray(light_sh), np.ascontiguousarray(y), out)
    return out
