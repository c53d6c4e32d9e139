"""Benchmarks of prtlab.wavelet: batched 2D Haar transforms of 6x32x32 cubemaps (peer: PyWavelets,
or the float64 reference tier without it), Haar triple products (peer: the brute-force reference that
reconstructs the texels), and the per-vertex 8-bit sparse relighting dot product (peer: the same transfer
decoded once into a scipy.sparse CSR matrix, times the light)."""

from __future__ import annotations

import numpy as np

from prtlab.bench import case, check_same_work, floor, transfer_csr
from prtlab.wavelet import encode_transfer, haar2d, ihaar2d, triple_product

RES = 32
TEXELS = 6 * RES * RES
# flops per texel of one transform: per level and 2x2 block 4 outputs of 3 adds + 1 multiply
# (16 flops per 4 texels), over levels 1 + 1/4 + 1/16 + ... = 4/3
HAAR_FLOPS_PER_TEXEL = 4.0 * 4.0 / 3.0
# flops per quadtree node of one triple product: 9 scalings, 3 x 5 for the pair terms, 3 for their
# weights, 12 for the three-distinct-types terms, 3 x 4 x 4 for the children's means
TRIPLE_FLOPS_PER_NODE = 9 + 15 + 3 + 12 + 48


def _cubemaps(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.random((n, 6, RES, RES))


def _haar_peer(x: np.ndarray, inverse: bool):
    try:
        import pywt

        if not inverse:
            return ("pywt.wavedec2 (haar, periodization)",
                    lambda: pywt.wavedec2(x, "haar", mode="periodization", axes=(-2, -1)))
        coeffs = pywt.wavedec2(x, "haar", mode="periodization", axes=(-2, -1))
        return ("pywt.waverec2 (haar, periodization)",
                lambda: pywt.waverec2(coeffs, "haar", mode="periodization", axes=(-2, -1)))
    except ImportError:  # pragma: no cover - PyWavelets is a test extra
        return (f"prtlab {'ihaar2d' if inverse else 'haar2d'} method='reference'",
                lambda: (ihaar2d if inverse else haar2d)(x, method="reference"))


def _haar_case(quick: bool, inverse: bool) -> dict:
    """The forward transform of 10k (quick: 1k) random cubemaps, or the inverse of their coefficients,
    against :func:`_haar_peer`."""
    n = 1_000 if quick else 10_000
    x = _cubemaps(n, 2 if inverse else 1)
    if inverse:
        x = haar2d(x)
    return {
        "run": (lambda: ihaar2d(x)) if inverse else (lambda: haar2d(x)),
        "gflop": n * TEXELS * HAAR_FLOPS_PER_TEXEL / 1e9,
        "items": n,
        "peer": _haar_peer(x, inverse),
    }


@case("wavelet.haar.forward.10k")
def haar_forward(quick: bool) -> dict:
    return _haar_case(quick, inverse=False)


@case("wavelet.haar.inverse.10k")
def haar_inverse(quick: bool) -> dict:
    return _haar_case(quick, inverse=True)


@case("wavelet.triple.6x32x32")
def triple(quick: bool) -> dict:
    """Triple products of whole cubemaps; the peer is the brute-force reference on the same count."""
    n = 500 if quick else 2_000
    a, b, c = (haar2d(_cubemaps(n, s)) for s in (3, 4, 5))
    nodes = 6 * (RES * RES - 1) // 3
    return {
        "run": lambda: triple_product(a, b, c),
        "gflop": n * nodes * TRIPLE_FLOPS_PER_NODE / 1e9,
        "items": n,
        "peer": ("triple_product method='reference' (reconstruct, multiply, sum)",
                 lambda: triple_product(a, b, c, method="reference")),
    }


@case("wavelet.sparse_dot.portal.10k")
def sparse_dot(quick: bool) -> dict:
    """Per-frame direct light of 10k vertices that see a small portal (a few dozen cells each)."""
    n = 2_000 if quick else 10_000
    rng = np.random.default_rng(6)
    transfer = np.zeros((n, 6, RES, RES))
    for v in range(n):
        size = rng.integers(2, 9, size=2)
        i0, j0 = rng.integers(0, RES - size + 1)
        transfer[v, 2, i0 : i0 + size[0], j0 : j0 + size[1]] = rng.random(tuple(size))
    sparse = encode_transfer(transfer)
    light = rng.random((6, RES, RES, 3))
    light_haar = haar2d(light, channels=True)
    csr = transfer_csr(sparse)
    stacked = np.concatenate([light.reshape(TEXELS, 3), light_haar.reshape(TEXELS, 3)])
    check_same_work(sparse.dot(light, light_haar), csr @ stacked, "wavelet.sparse_dot")
    return {
        "run": lambda: sparse.dot(light, light_haar),
        "gflop": 2 * 3 * sparse.codes.size / 1e9,
        "items": n,
        "peer": ("scipy.sparse CSR float64 @ light", lambda: csr @ stacked),
        # floor: 2 x 3 flops a stored entry; the stored transfer read once, the light (pulse and Haar) read and
        # the radiance written (SparseTransfer.nbytes + 2 T 3 8 + 24 V bytes)
        "floor": floor(6.0 * sparse.codes.size, sparse.nbytes + 2 * TEXELS * 3 * 8 + 24 * n,
                       "6 E flops; SparseTransfer.nbytes + 48 T + 24 V bytes"),
        "stored_bytes": sparse.nbytes,
    }
