"""Numba kernels of the portals pipeline's per-frame passes (arrays and scalars only, no checks)."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, parallel=True)
def indirect_pass_kernel(transfer, light_sh, out):
    """out[v, c] += sum_i transfer[v, i, c] * light_sh[i, c] (float32 transfer, float64 sums)."""
    n_vertices, n_coeffs, n_channels = transfer.shape
    for v in numba.prange(n_vertices):
        for c in range(n_channels):
            acc = 0.0
            for i in range(n_coeffs):
                acc += np.float64(transfer[v, i, c]) * light_sh[i, c]
            out[v, c] += acc
