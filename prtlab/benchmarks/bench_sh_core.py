"""Benchmarks of the SH core: basis evaluation (peer: sphericart), batched rotation (peer: one BLAS matrix
product with the block-diagonal rotation matrix) and the projection of an equirect sky (peer: the same rule summed
pixel by pixel)."""

from __future__ import annotations

import numpy as np

from prtlab.bench import case, check_same_work, floor
from prtlab.geometry import equirect_directions, equirect_solid_angles
from prtlab.sh import basis, project, project_equirect, rotate, rotation_matrix


def _directions(n: int) -> np.ndarray:
    rng = np.random.default_rng(1)
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _basis_flops(order: int) -> int:
    """Estimated flops per direction of the fast tier.

    Normalisation ~10; per (l, m >= 0) pair ~6 (recurrence step 4, two output
    products); per m ~6 (complex product for (x + i y)^m). The hand-written
    bands l <= 3 cost less than this recurrence count, so it is an upper estimate.
    """
    return 10 + 3 * order * (order + 1) + 6 * order


def _basis_case(order: int, quick: bool) -> dict:
    n = 100_000 if quick else 1_000_000
    dirs = _directions(n)
    peer = None
    try:
        import sphericart

        # sphericart 2.x: SphericalHarmonics(l_max) is the normalised real SH (same basis
        # and order as prtlab); it runs on all cores with OpenMP, as our kernel does with numba.
        calc = sphericart.SphericalHarmonics(order - 1)
        peer = ("sphericart.SphericalHarmonics", lambda: calc.compute(dirs))
    except ImportError:  # pragma: no cover - sphericart is a test extra
        pass
    return {
        "run": lambda: basis(dirs, order),
        "gflop": n * _basis_flops(order) / 1e9,
        "items": n,
        "peer": peer,
    }


@case("sh.basis.order4.1M")
def basis_order4(quick: bool) -> dict:
    return _basis_case(4, quick)


@case("sh.basis.order8.1M")
def basis_order8(quick: bool) -> dict:
    return _basis_case(8, quick)


@case("sh.rotate.order4.100k")
def rotate_order4(quick: bool) -> dict:
    order = 4
    n = 100_000
    rng = np.random.default_rng(2)
    coeffs = rng.normal(size=(n, order * order))
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.diag(r))
    if np.linalg.det(R) < 0:
        R[:, 0] = -R[:, 0]
    # the peer: the block-diagonal matrix (built once, as a user rotating many batches by one R would) applied
    # with one BLAS GEMM; applying each band's (2l+1)^2 block to its strided column slice is slower in numpy
    dense_t = np.ascontiguousarray(rotation_matrix(R, order).T)
    block_macs = sum((2 * l + 1) ** 2 for l in range(order))
    check_same_work(rotate(coeffs, R), coeffs @ dense_t, "sh.rotate")
    return {
        "run": lambda: rotate(coeffs, R),
        "gflop": 2 * n * block_macs / 1e9,
        "items": n,
        "peer": ("BLAS GEMM, batch @ block-diagonal D(R)^T", lambda: coeffs @ dense_t),
        # floor: each band's (2l+1)^2 block applied to every vector (the blocks built once, not counted); the
        # batch read and written once
        "floor": floor(2 * n * block_macs, 16 * n * order * order,
                       "2 B sum_l (2l+1)^2 flops; 16 n^2 B bytes"),
    }


@case("sh.project.equirect.256x512.order10")
def project_equirect_order10(quick: bool) -> dict:
    """A new sky's projection, as the spherical lights make it every frame the sky changes (order 10)."""
    order, h, w = 10, 256, 512
    image = np.random.default_rng(3).random((h, w, 3))
    # the peer: the same rule summed pixel by pixel (prtlab.sh.basis at every pixel, one product per chunk), its
    # directions and weights made once, as a user projecting many skies of one size would
    dirs, weights = equirect_directions(h, w).reshape(-1, 3), equirect_solid_angles(h, w).reshape(-1)
    values = image.reshape(-1, 3)
    check_same_work(project_equirect(image, order), project(values, dirs, weights, order), "sh.project.equirect")
    return {
        "run": lambda: project_equirect(image, order),
        "items": h * w,
        "peer": ("the pixel sum, sh.project at every pixel", lambda: project(values, dirs, weights, order)),
        "floor": floor(nbytes=8 * h * w * 3, formula="the map read once: 8 H W C B"),
    }
