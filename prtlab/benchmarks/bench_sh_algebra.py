"""Benchmarks of the SH algebra: order-4 products (peer: numpy outer products and one GEMM with the Gaunt
tensor as an ``(n^4, n^2)`` matrix) and OL / HYB exponentials (peers: their numpy reference tiers).

Inputs of the exponentials are what the papers feed them: sums of 1..20
blocker logs (angular radius 5..60 degrees, random directions), order 4.
"""

from __future__ import annotations

import numpy as np

from prtlab.bench import case, check_same_work, floor
from prtlab.sh import exp, gaunt_tensor, product
from prtlab.sh._explog import _HYB_THRESHOLD, _blocker_sums

ORDER = 4


def _batch(quick: bool) -> int:
    return 20_000 if quick else 100_000


def _product_flops(order: int) -> int:
    """Flops of one truncated product: 3 per Gaunt entry (two multiplies, one add)."""
    return 3 * gaunt_tensor(order).nnz


def _square_flops(order: int) -> int:
    """Flops of one truncated square ``a * a`` at least: 2 per Gaunt entry with ``i <= j`` (the factor 2 of
    ``i < j`` folded into the tensor; the products ``a_i a_j``, shared over ``k``, not counted)."""
    g = gaunt_tensor(order)
    n2 = order * order
    dense = g.dense()[:n2, :n2, :n2]
    return 2 * int(np.count_nonzero(np.triu(np.ones((n2, n2), bool))[:, :, None] & (dense != 0)))


# Floors (``prtlab.bench.floor``) of a batch of B order-n vectors (n^2 coefficients, float64): a product reads two
# and writes one (24 n^2 B bytes) and does 3 flops a Gaunt non-zero; an exponential reads one and writes one
# (16 n^2 B) and does at least OL's 3 n^2 (norm of f^, scale, DC term; the table lookup not counted) plus, for HYB,
# each item's own squarings (ceil(log2(|f^| / 0.125)), not its tile's largest) at the symmetric square's flops.
PRODUCT_FORMULA = "3 nnz(G) B flops; 24 n^2 B bytes"
EXP_FORMULA = "3 n^2 B (+ sum of squarings x symmetric square flops, HYB) flops; 16 n^2 B bytes"


def _log_visibility(n: int) -> np.ndarray:
    rng = np.random.default_rng(2006)
    base = _blocker_sums(rng, min(n, 5000), ORDER)
    return np.ascontiguousarray(base[np.arange(n) % base.shape[0]])


@case("sh.product.order4.100k")
def product_order4(quick: bool) -> dict:
    n = _batch(quick)
    rng = np.random.default_rng(3)
    a = rng.normal(size=(n, ORDER * ORDER))
    b = rng.normal(size=(n, ORDER * ORDER))
    n2 = ORDER * ORDER
    gaunt = np.ascontiguousarray(gaunt_tensor(ORDER).dense()[:n2, :n2, :n2].reshape(n2 * n2, n2))

    def peer():  # c_k = sum_ij a_i b_j G_ijk: the batch's outer products (B, n^4) times G (n^4, n^2)
        return (a[:, :, None] * b[:, None, :]).reshape(n, n2 * n2) @ gaunt

    check_same_work(product(a, b), peer(), "sh.product")
    return {
        "run": lambda: product(a, b),
        "gflop": n * _product_flops(ORDER) / 1e9,
        "items": n,
        "peer": ("numpy outer products @ Gaunt (n^4, n^2) GEMM", peer),
        "floor": floor(n * _product_flops(ORDER), 24 * n2 * n, PRODUCT_FORMULA),
    }


@case("sh.exp.ol.order4.100k")
def exp_ol_order4(quick: bool) -> dict:
    n = _batch(quick)
    f = _log_visibility(n)
    n2 = ORDER * ORDER
    # norm (2 per coefficient), table lookup (~15), scale and DC (~n2 + 20)
    flops = 3 * n2 + 35
    return {
        "run": lambda: exp(f, method="ol"),
        "gflop": n * flops / 1e9,
        "items": n,
        "peer": ("numpy reference tier (method='ol-reference')", lambda: exp(f, method="ol-reference")),
        "floor": floor(3 * n2 * n, 16 * n2 * n, EXP_FORMULA),
    }


@case("sh.exp.hyb.order4.100k")
def exp_hyb_order4(quick: bool) -> dict:
    n = _batch(quick)
    f = _log_visibility(n)
    r = np.linalg.norm(f[:, 1:], axis=1)
    k = np.where(r > _HYB_THRESHOLD, np.ceil(np.log2(np.maximum(r, 1e-300) / _HYB_THRESHOLD)), 0.0)
    # the kernel squares whole tiles of 64 items together, up to the tile's largest k
    tiles = np.array_split(k, max(1, int(np.ceil(n / 64))))
    squarings = sum(float(t.max()) * t.size for t in tiles)
    flops = n * (3 * ORDER * ORDER + 35) + squarings * _product_flops(ORDER)
    return {
        "run": lambda: exp(f, method="hyb"),
        "gflop": flops / 1e9,
        "items": n,
        "peer": ("numpy reference tier (method='hyb-reference')", lambda: exp(f, method="hyb-reference")),
        "floor": floor(3 * ORDER**2 * n + k.sum() * _square_flops(ORDER), 16 * ORDER**2 * n, EXP_FORMULA),
    }
