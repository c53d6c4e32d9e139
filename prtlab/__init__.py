"""prtlab: CPU reference implementations of precomputed radiance transfer for dynamic scenes.

Entry points::

    scene = prtlab.load_scene("scene.yaml")
    res = prtlab.shade(scene, method="reference", bounces=1)
    img = prtlab.render_image(scene, res)
    print(prtlab.compare(res, reference).table())   # per-object errors (prtlab.metrics)

Building blocks live in subpackages: :mod:`prtlab.sh`, :mod:`prtlab.wavelet`,
:mod:`prtlab.brdf`, :mod:`prtlab.pca`, :mod:`prtlab.geometry`,
:mod:`prtlab.scene`; pipelines in :mod:`prtlab.shadowfields`,
:mod:`prtlab.interreflection`, :mod:`prtlab.spherelights`,
:mod:`prtlab.portals`; ground truth in :mod:`prtlab.reference`.
Subpackages are imported on first use, so ``import prtlab`` is cheap.
"""

from __future__ import annotations

import importlib
import os

__version__ = "0.1.0"

# numba's OpenMP threads spin after each parallel loop by default and then compete with OpenBLAS's and
# Embree's threads for the two cores: a frame of a few hundred short parallel loops ran 4x slower on two
# threads than on one (docs/DECISIONS.md). Sleeping at once costs microseconds per loop. It takes effect
# when prtlab is imported before the OpenMP runtime loads; the user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# OpenBLAS's workers likewise busy-wait about 2**28 cycles after each call, on the cores numba's threads need
# next; 2**16 keeps them awake between close calls (docs/DECISIONS.md). It takes effect when prtlab is
# imported before numpy loads OpenBLAS; the user's own setting wins.
os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "16")

_SUBPACKAGES = {
    "sh", "wavelet", "brdf", "pca", "geometry", "scene", "shadowfields", "interreflection",
    "spherelights", "portals", "reference", "render", "cache", "pipeline", "api", "metrics", "data",
}
_API = {
    "load_scene": "prtlab.scene",
    "Scene": "prtlab.scene",
    "ShadeResult": "prtlab.scene",
    "shade": "prtlab.api",
    "render_image": "prtlab.api",
    "precompute": "prtlab.api",
    "compare": "prtlab.metrics",
}

__all__ = sorted(_SUBPACKAGES | set(_API))


def __getattr__(name: str):
    if name in _SUBPACKAGES:
        return importlib.import_module(f"prtlab.{name}")
    if name in _API:
        return getattr(importlib.import_module(_API[name]), name)
    raise AttributeError(f"module 'prtlab' has no attribute {name!r}")


def __dir__():
    return __all__
