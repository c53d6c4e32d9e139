"""The elementary functions written as inline numba code (``prtlab.spherelights._libm``) against libm's: each within
two units in the last place over its range, at random points, at the switches between its branches and at the
range's ends."""

import math

import numba
import numpy as np

from prtlab.spherelights._libm import asin_unit, atan_nonneg, sincos_quarter


def _ulps(ours, exact):
    return np.abs(ours - exact) / np.spacing(np.abs(exact))


@numba.njit
def _asin(x):
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        out[i] = asin_unit(x[i])
    return out


@numba.njit
def _sincos(e):
    s, c = np.empty_like(e), np.empty_like(e)
    for i in range(e.shape[0]):
        s[i], c[i] = sincos_quarter(e[i])
    return s, c


@numba.njit
def _atan(t):
    out = np.empty_like(t)
    for i in range(t.shape[0]):
        out[i] = atan_nonneg(t[i])
    return out


def _around(points, width, n, rng):
    return np.concatenate([p + width * rng.uniform(-1.0, 1.0, n) for p in points])


def test_asin_unit_is_within_two_units_in_the_last_place_of_libm():
    """``asin_unit`` (the blockers' angular radius) against numpy's ``arcsin`` on ``[0, 1]``: random points, both
    sides of the switch at 0.5, near 1, and the ends (0 and 1 exactly: 0 and ``pi / 2``)."""
    rng = np.random.default_rng(3)
    half = np.nextafter(0.5, np.array([0.0, 1.0]))
    x = np.concatenate([rng.random(200_000), 0.5 + 1e-3 * rng.standard_normal(20_000).clip(-0.5, 0.5),
                        1.0 - 1e-9 * rng.random(1_000), [0.0, 5e-324, 1e-300, 0.5, *half, 1.0]])
    x = x[(x >= 0.0) & (x <= 1.0)]
    exact = np.arcsin(x)
    assert _ulps(_asin(x), exact).max() <= 2.0
    assert _asin(np.array([0.0, 1.0])).tolist() == [0.0, np.pi / 2]


def test_sincos_quarter_is_within_two_units_in_the_last_place_of_libm():
    """``sincos_quarter`` (the ground samples' elevations) against ``math.sin`` and ``math.cos`` on ``[0, pi/2]``:
    random points, both sides of the switch at ``pi/4``, next to ``pi/2`` (where the cosine is small and carries the
    tail of ``pi/2``) and the ends."""
    rng = np.random.default_rng(4)
    e = np.concatenate([rng.uniform(0.0, np.pi / 2, 300_000), _around([np.pi / 4], 1e-9, 10_000, rng),
                        np.pi / 2 - 1e-6 * rng.random(10_000), np.pi / 2 - 1e-14 * rng.random(1_000),
                        [0.0, 5e-324, 1e-300, 1e-8, np.pi / 4, *np.nextafter(np.pi / 4, [0.0, 1.0]),
                         np.nextafter(np.pi / 2, 0.0), np.pi / 2]])
    e = e[(e >= 0.0) & (e <= np.pi / 2)]
    s, c = _sincos(e)
    ref_s = np.array([math.sin(v) for v in e])
    ref_c = np.array([math.cos(v) for v in e])
    assert _ulps(s[ref_s > 0], ref_s[ref_s > 0]).max() <= 2.0
    assert _ulps(c, ref_c).max() <= 2.0
    assert (s[e == 0.0] == 0.0).all() and (c[e == 0.0] == 1.0).all()


def test_atan_nonneg_is_within_two_units_in_the_last_place_of_libm():
    """``atan_nonneg`` (the ground samples' elevation spans) against ``math.atan`` on ``[0, inf]``: random points
    over 40 decades, both sides of each of fdlibm's switches (7/16, 11/16, 19/16, 39/16), and 0 and infinity."""
    rng = np.random.default_rng(5)
    t = np.concatenate([rng.uniform(0.0, 4.0, 200_000), 10.0 ** rng.uniform(-20.0, 20.0, 200_000),
                        _around([0.4375, 0.6875, 1.1875, 2.4375], 1e-9, 10_000, rng),
                        [0.0, 5e-324, 1e-300, 0.4375, 0.6875, 1.1875, 2.4375, 1e300, np.inf]])
    t = t[t >= 0.0]
    ref = np.array([math.atan(v) for v in t])
    ours = _atan(t)
    positive = ref > 0
    assert _ulps(ours[positive], ref[positive]).max() <= 2.0
    assert ours[t == 0.0].tolist() == [0.0] and ours[t == np.inf].tolist() == [math.atan(np.inf)]
