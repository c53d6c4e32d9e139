"""Numba kernels of the portals pipeline's per-frame passes (arrays and scalars only, no checks)."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, parallel=True)
def indirect_pass_kernel(transfer, light_sh, out):
    """out[v, c] += sum_i transfer[v, i, c] * light_sh[i, c], c in 0..2 (float32 transfer, float64 sums)."""
    n_vertices, n_coeffs, n_channels = transfer.shape
    for v in numba.prange(n_vertices):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        for i in range(n_coeffs):  # memory order: (i, c) contiguous per vertex
            a0 += transfer[v, i, 0] * light_sh[i, 0]
            a1 += transfer[v, i, 1] * light_sh[i, 1]
            a2 += transfer[v, i, 2] * light_sh[i, 2]
        out[v, 0] += a0
        out[v, 1] += a1
        out[v, 2] += a2
