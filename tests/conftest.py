"""Shared test configuration: seeds, tolerances and hypothesis profiles live here only."""

from __future__ import annotations

import os

import numba
import numpy as np
import pytest
from hypothesis import HealthCheck, settings

# Tests never read or write the user's cache: every precomputation a test caches goes to a folder of
# this checkout (shared by the xdist workers of one run; entries are keyed by the code that made them).
os.environ["PRTLAB_CACHE"] = os.environ.get(
    "PRTLAB_TEST_CACHE", os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".pytest_cache",
                                      "prtlab-cache")
)

# One place for tolerances (per dtype), as e3nn's FLOAT_TOLERANCE.
FLOAT_TOLERANCE = {np.float64: 1e-10, np.float32: 1e-4}

# Monte Carlo comparisons: |estimate - truth| <= MC_SIGMAS * standard error.
MC_SIGMAS = 4.0

# The default profile is derandomized: the same examples on every run, so CI is reproducible;
# the "thorough" profile explores new random examples (PRTLAB_HYPOTHESIS_PROFILE=thorough).
settings.register_profile(
    "default", max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile(
    "thorough", max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile(os.environ.get("PRTLAB_HYPOTHESIS_PROFILE", "default"))


@pytest.fixture
def rng() -> np.random.Generator:
    """A freshly seeded generator per test: reproducible, never global state."""
    return np.random.default_rng(20070625)


def random_directions(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) uniformly distributed unit vectors."""
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed (3, 3) rotation matrix (QR of a Gaussian matrix)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


@numba.njit(parallel=True)
def _fill(x):
    for i in numba.prange(x.shape[0]):
        x[i] = i


def two_numba_threads():
    """Two numba threads for a test of tasks, and a parallel kernel run so that numba's threading layer is chosen;
    skips on one core or numba's ``workqueue`` layer (no tasks there: ``prtlab._tasks``)."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs 2 numba threads (one core here)")
    numba.set_num_threads(2)
    _fill(np.zeros(4))
    if numba.threading_layer() == "workqueue":
        pytest.skip("numba's workqueue layer: no tasks")
