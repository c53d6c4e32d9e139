"""The sky's bands above the SH order through a flat occluder's hard horizon (an extension of Iwasaki et al.
2007; option ``horizon_sky``).

At a point that takes a flat occluder's half-space (``flat_visibility="plane"``, :mod:`._flat`) the environment
reaches the order-n transfer ``P_n(V g_k cos)`` only through its bands below n. Against the smooth ``g_k cos``
alone the higher bands add little, but the plane's hard horizon carries them into the light: under a clear sky
(sun 30 degrees up) the sides' bottom row of a box resting on a floor got 11 % too little direct light at order 4
(``docs/notes/interreflection.md``). At such points this adds, per term ``k``, the light of those bands through
the point's half-spaces,

    dL_k = int (L - L_n)(w) H(w) g_k(R^T w) max(0, n . w) dw,

``L_n`` the environment's order-n SH, ``H`` the product of the point's half-spaces and ``R`` its local frame, summed
over cells of the map (:func:`sky_cells`): ``dL = W r`` with the cells' weights ``W`` (:func:`horizon_weights`, made
per pose) and residual radiance ``r`` (per environment). The transfer keeps the bands below n and every other
occluder; the added light is exact where the planes are the point's only occluders and counts no other occluder.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numba
import numpy as np

from prtlab import sh
from prtlab.brdf import Lambert, local_frame
from prtlab.geometry import equirect_directions, equirect_solid_angles

#: Rows of the quadrature's cells: a map with fewer rows is sampled (bilinearly, as it is lit) on a map of this
#: many; a larger one is summed into cells of ``k x k`` pixels, ``k = ceil(H / CELL_ROWS)``.
CELL_ROWS = 64
_CHUNK = 64  # distinct normals per block of the (normals, cells) weights
_UP = np.array([[0.0, 0.0, 1.0]])  # a local direction (a Lambertian g is the same at every one)


@functools.lru_cache(maxsize=8)
def _grid(height: int, width: int, cell_rows: int) -> tuple:
    """``(h, w, k, pixel_omega, dirs, omega)`` of the cells of an ``height x width`` map: the map sampled on ``(h,
    w)`` (itself, or ``cell_rows`` rows if it has fewer), ``k`` its pixels per cell side, their solid angles ``(h,
    w)``, the cells' unit mean directions ``(Q, 3)`` and solid angles ``(Q,)`` (read-only)."""
    h, w = (height, width) if height >= cell_rows else (cell_rows, max(width * cell_rows // height, 1))
    k = -(-h // cell_rows)
    pixel_omega = equirect_solid_angles(h, w)
    mean = _block_sums(equirect_directions(h, w) * pixel_omega[..., None], k).reshape(-1, 3)
    dirs = mean / np.linalg.norm(mean, axis=1, keepdims=True)
    omega = _block_sums(pixel_omega, k).reshape(-1)
    for a in (pixel_omega, dirs, omega):
        a.setflags(write=False)
    return h, w, k, pixel_omega, dirs, omega


def _block_sums(a, k: int) -> np.ndarray:
    """Sums of ``a (H, W, ...)`` over blocks of ``k x k`` entries (the last row and column of blocks padded with 0)."""
    if k == 1:
        return a
    h, w = a.shape[:2]
    a = np.pad(a, ((0, -h % k), (0, -w % k)) + ((0, 0),) * (a.ndim - 2))
    return a.reshape(a.shape[0] // k, k, a.shape[1] // k, k, *a.shape[2:]).sum(axis=(1, 3))


def sky_cells(env, env_sh, cell_rows: int = CELL_ROWS) -> tuple[tuple, np.ndarray, np.ndarray]:
    """``(grid, dirs (Q, 3), residual (Q, 3))`` for environment light ``env`` (an
    :class:`prtlab.scene.EnvironmentLight`) whose SH is ``env_sh (n^2, 3)``: its cells' grid (a key: maps of one
    size share their cells), their directions and each cell's ``(L - L_n) dw``.

    A cell holds ``k x k`` of the map's pixels (``k = ceil(H / cell_rows)``), with the weights of
    :func:`prtlab.geometry.equirect_solid_angles` (exact for its bilinear interpolant along rows), at their mean
    direction: their radiance times solid angle is kept. A map under ``cell_rows`` rows is first sampled on one of
    that many. A constant environment has no higher bands: no cells."""
    env_sh = np.asarray(env_sh, dtype=np.float64)
    if env.constant is not None:
        return (), np.zeros((0, 3)), np.zeros((0, 3))
    image = np.asarray(env.image, dtype=np.float64)
    grid = (*image.shape[:2], int(cell_rows))
    h, w, k, pixel_omega, dirs, omega = _grid(*grid)
    if h != image.shape[0]:
        image = env.radiance(equirect_directions(h, w))
    energy = _block_sums(image * pixel_omega[..., None], k).reshape(-1, 3)
    residual = energy - (sh.basis(dirs, math.isqrt(len(env_sh))) @ env_sh) * omega[:, None]
    return grid, dirs, residual


class HorizonGroup(NamedTuple):
    """The weights of the points that take one set of half-spaces: ``dL[points] = (weights @ residual[cells])
    [which]`` (:func:`horizon_weights`)."""

    points: np.ndarray  # (P,) the receiver's points
    which: np.ndarray  # (P,) each one's row of weights (points of one normal share one)
    cells: np.ndarray  # (C,) the cells every half-space of the set lets through
    weights: np.ndarray  # (U, K, C) float32


def horizon_weights(normals, rows, axes, sep, dirs) -> list[HorizonGroup]:
    """The cells' weights of the points that take half-spaces, one :class:`HorizonGroup` per set of half-spaces,
    so that ``dL = weights @ residual`` (:func:`sky_cells`' cells ``dirs`` and residual; see the module).

    ``normals (V, 3)``: the receiver's unit normals; ``rows (M,)`` and ``axes (M, 3)``: each half-space a point
    takes and the unit side it sees (a point may take several); ``sep``: its :class:`prtlab.brdf.SeparableBRDF`
    (a Lambertian one's ``g`` is one constant, read once). Points with one normal and one set of half-spaces share
    a row of weights, and a row keeps only the cells the set lets through. The weights are float32 (relative
    rounding ``2^-24`` of each of ``dL``'s terms, far under the quadrature's error; :func:`horizon_sums` sums them
    in float64)."""
    rows = np.asarray(rows, dtype=np.int64)
    points, pair = np.unique(rows, return_inverse=True)
    if not len(points):
        return []
    axes = np.asarray(axes, dtype=np.float64)
    order = np.lexsort((*axes.T[::-1], pair))  # each point's half-spaces, sorted: one key per set
    slot = np.arange(len(rows)) - np.searchsorted(pair[order], pair[order])
    sides = np.zeros((len(points), 3 * (int(slot.max()) + 1)))
    for j, k in zip(order, slot):
        sides[pair[j], 3 * k:3 * k + 3] = axes[j]
    lambert = isinstance(sep.brdf, Lambert)
    groups = []
    sets, member = np.unique(sides, axis=0, return_inverse=True)
    for i, sides_i in enumerate(sets):
        mine = np.flatnonzero(member.reshape(-1) == i)
        cells = np.flatnonzero(np.all([dirs @ sides_i[a:a + 3] > 0.0 for a in range(0, len(sides_i), 3)
                                       if np.any(sides_i[a:a + 3] != 0.0)], axis=0))
        d = dirs[cells]
        distinct, which = np.unique(np.asarray(normals, dtype=np.float64)[points[mine]], axis=0, return_inverse=True)
        weights = np.empty((len(distinct), sep.K, len(cells)), dtype=np.float32)
        for s in range(0, len(distinct), _CHUNK):
            n = distinct[s:s + _CHUNK]
            cos = np.maximum(n @ d.T, 0.0)  # (U, C): max(0, n . w)
            if lambert:  # g is one constant
                weights[s:s + len(n), 0] = cos * sep.g(_UP)[0, 0]
            else:  # g_k(R^T w)
                weights[s:s + len(n)] = np.einsum("pq,pqk->pkq", cos,
                                                  sep.g(np.einsum("pji,qj->pqi", local_frame(n), d)))
        groups.append(HorizonGroup(points[mine], which.reshape(-1), cells, weights))
    return groups


def horizon_sums(group: HorizonGroup, residual, method: str = "numba") -> np.ndarray:
    """``dL (P, K, 3)`` of ``group``'s points: its weights times :func:`sky_cells`' ``residual (Q, 3)`` at its cells,
    each point's row. ``"numba"``: a kernel summing in float64 in any order (parallel over the rows, no BLAS: it
    runs between a frame's tasks); ``"reference"``: numpy's float64 product, the specification."""
    u, k, c = group.weights.shape
    rows = group.weights.reshape(u * k, c)
    if method == "reference":
        out = rows.astype(np.float64) @ np.asarray(residual, dtype=np.float64)[group.cells]
    else:
        out = np.empty((u * k, 3))
        _sums_kernel(rows, np.ascontiguousarray(np.asarray(residual, dtype=np.float64)[group.cells].T), out)
    return out.reshape(u, k, 3)[group.which]


@numba.njit(cache=True, inline="always")
def _add_row(w, r0, r1, r2, a0, a1, a2):
    """``(a0, a1, a2) + w (r0, r1, r2)``, ``w`` read as float64."""
    w = np.float64(w)
    return a0 + w * r0, a1 + w * r1, a2 + w * r2


@numba.njit(cache=True, parallel=True, nogil=True, fastmath={"reassoc", "contract"})
def _sums_kernel(weights, residual_t, out):
    """``out[u, c] = sum_q weights[u, q] residual_t[c, q]`` for the 3 channels of ``residual_t`` (3, Q): float32
    weights read as float64, float64 sums (their order free: SIMD lanes). Rows go in blocks of 4, 12 sums held in
    registers, so each residual value loaded serves 4 rows (the residual, 3 x 4,096 float64, is larger than a
    core's L1 cache); the last block's leftover rows one at a time."""
    n_rows = weights.shape[0]
    for b in numba.prange((n_rows + 3) // 4):
        u = 4 * b
        if u + 4 <= n_rows:
            a00 = a01 = a02 = a10 = a11 = a12 = a20 = a21 = a22 = a30 = a31 = a32 = 0.0
            for q in range(weights.shape[1]):
                r0, r1, r2 = residual_t[0, q], residual_t[1, q], residual_t[2, q]
                a00, a01, a02 = _add_row(weights[u, q], r0, r1, r2, a00, a01, a02)
                a10, a11, a12 = _add_row(weights[u + 1, q], r0, r1, r2, a10, a11, a12)
                a20, a21, a22 = _add_row(weights[u + 2, q], r0, r1, r2, a20, a21, a22)
                a30, a31, a32 = _add_row(weights[u + 3, q], r0, r1, r2, a30, a31, a32)
            out[u, 0], out[u, 1], out[u, 2] = a00, a01, a02
            out[u + 1, 0], out[u + 1, 1], out[u + 1, 2] = a10, a11, a12
            out[u + 2, 0], out[u + 2, 1], out[u + 2, 2] = a20, a21, a22
            out[u + 3, 0], out[u + 3, 1], out[u + 3, 2] = a30, a31, a32
        else:
            for v in range(u, n_rows):
                a0 = a1 = a2 = 0.0
                for q in range(weights.shape[1]):
                    a0, a1, a2 = _add_row(weights[v, q], residual_t[0, q], residual_t[1, q], residual_t[2, q],
                                          a0, a1, a2)
                out[v, 0], out[v, 1], out[v, 2] = a0, a1, a2
