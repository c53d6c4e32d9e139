"""Benchmarks of prtlab.brdf: batched Phong evaluation, the separable factorisation, g_k cos projection."""

from __future__ import annotations

import numpy as np

from prtlab.bench import case
from prtlab.brdf import phong, project_g_cos, separable


def _directions(n: int, seed: int) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@case("brdf.phong.eval.1M")
def phong_eval(quick: bool) -> dict:
    n = 200_000 if quick else 1_000_000
    wi, wo, normal = _directions(n, 1), _directions(n, 2), _directions(n, 3)
    b = phong([0.2, 0.3, 0.1], [0.5, 0.4, 0.6], 32.0)
    # per pair: 2 dots (10), reflection dot (12), pow (~20), 3 channels (9)
    return {
        "run": lambda: b.eval(wi, wo, normal),
        "gflop": n * 51 / 1e9,
        "items": n,
        "peer": ("numpy float64 tier", lambda: b.eval(wi, wo, normal, method="reference")),
    }


@case("brdf.separable.e64.K8")
def separable_fit(quick: bool) -> dict:
    resolution = (32, 64) if quick else (64, 128)
    b = phong(0.0, 1.0, 64.0)
    return {"run": lambda: separable(b, 8, resolution=resolution), "gflop": None, "items": None, "peer": None}


@case("brdf.project_g_cos.order5.K4.100k")
def g_cos_projection(quick: bool) -> dict:
    n = 20_000 if quick else 100_000
    sep = separable(phong(0.3, 0.6, 16.0), 4, resolution=(32, 64))
    normals = _directions(n, 4)
    return {"run": lambda: project_g_cos(sep, normals, 5), "gflop": None, "items": n, "peer": None}
