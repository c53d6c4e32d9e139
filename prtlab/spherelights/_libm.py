"""Elementary functions as inline numba code, so that loops over them vectorise (libm's are calls LLVM keeps scalar,
and numba here has no vector library).

Each is fdlibm's algorithm (FreeBSD msun: ``e_asin.c``, ``k_sin.c``, ``k_cos.c``, ``s_atan.c``) restricted to the
range its callers need, with the branches on the argument written as selects. Tests hold each within a few units in
the last place of libm's (``tests/spherelights/test_libm.py``).

fdlibm: Copyright (C) 1993 by Sun Microsystems, Inc. All rights reserved. Developed at SunSoft, a Sun Microsystems,
Inc. business. Permission to use, copy, modify, and distribute this software is freely granted, provided that this
notice is preserved.
"""

from __future__ import annotations

import math

import numba

_PIO2_HI, _PIO2_LO = 1.57079632679489655800e+00, 6.12323399573676603587e-17  # pi/2 = _PIO2_HI + _PIO2_LO
_PIO4 = 7.85398163397448278999e-01

# e_asin.c: asin(x) = x + x R(x^2) on [0, 0.5], R = P / Q, |error| < 2^-58.75
_AS_P = (1.66666666666666657415e-01, -3.25565818622400915405e-01, 2.01212532134862925881e-01,
         -4.00555345006794114027e-02, 7.91534994289814532176e-04, 3.47933107596021167570e-05)
_AS_Q = (-2.40339491173441421878e+00, 2.02094576023350569471e+00, -6.88283971605453293030e-01,
         7.70381505559019352791e-02)
# k_sin.c, k_cos.c: sin and cos on [-pi/4, pi/4] (polynomials of degree 13 and 14)
_SIN = (-1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04,
        2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10)
_COS = (4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05,
        -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11)
# s_atan.c: atan on [0, 7/16] by an odd polynomial of degree 23, above it about 1/2, 1, 3/2 and infinity
_ATAN = (3.33333333333329318027e-01, -1.99999999998764832476e-01, 1.42857142725034663711e-01,
         -1.11111104054623557880e-01, 9.09088713343650656196e-02, -7.69187620504482999495e-02,
         6.66107313738753120669e-02, -5.83357013379057348645e-02, 4.97687799461593236017e-02,
         -3.65315727442169155270e-02, 1.62858201153657823623e-02)
_ATAN_HI = (4.63647609000806093515e-01, 7.85398163397448278999e-01, 9.82793723247329054082e-01,
            1.57079632679489655800e+00)  # atan(1/2), atan(1), atan(3/2), atan(inf), high parts
_ATAN_LO = (2.26987774529616870924e-17, 3.06161699786838301793e-17, 1.39033110312309984516e-17,
            6.12323399573676603587e-17)


@numba.njit(cache=True, error_model="numpy", inline="always")
def asin_unit(x):
    """``asin(x)`` for ``0 <= x <= 1``: ``R`` on ``[0, 0.5]`` as ``x + x R(x^2)``, above as ``pi/2 - 2 asin(sqrt((1 -
    x) / 2))`` (fdlibm's form for ``x >= 0.975``, used down to 0.5)."""
    big = x > 0.5
    t = 0.5 * (1.0 - x) if big else x * x
    s = math.sqrt(t)
    r = (t * (_AS_P[0] + t * (_AS_P[1] + t * (_AS_P[2] + t * (_AS_P[3] + t * (_AS_P[4] + t * _AS_P[5])))))
         / (1.0 + t * (_AS_Q[0] + t * (_AS_Q[1] + t * (_AS_Q[2] + t * _AS_Q[3])))))
    return _PIO2_HI - (2.0 * (s + s * r) - _PIO2_LO) if big else x + x * r


@numba.njit(cache=True, error_model="numpy", inline="always")
def sincos_quarter(e):
    """``(sin e, cos e)`` for ``0 <= e <= pi/2``: the kernels at ``e`` up to ``pi/4``, above at ``pi/2 - e`` (its
    head ``_PIO2_HI - e`` exact, its tail carried) with sine and cosine swapped."""
    up = e > _PIO4
    head = _PIO2_HI - e
    x = head + _PIO2_LO if up else e
    y = _PIO2_LO - (x - head) if up else 0.0  # the tail: x + y = pi/2 - e to twice the precision
    z = x * x
    w = z * z
    r = _SIN[1] + z * (_SIN[2] + z * _SIN[3]) + z * w * (_SIN[4] + z * _SIN[5])
    v = z * x
    s = x - ((z * (0.5 * y - v * r) - y) - v * _SIN[0])
    r = z * (_COS[0] + z * (_COS[1] + z * _COS[2])) + w * w * (_COS[3] + z * (_COS[4] + z * _COS[5]))
    hz = 0.5 * z
    w = 1.0 - hz
    c = w + (((1.0 - w) - hz) + (z * r - x * y))
    return (c, s) if up else (s, c)


@numba.njit(cache=True, error_model="numpy", inline="always")
def atan_nonneg(t):
    """``atan(t)`` for ``t >= 0`` (``+inf`` included): fdlibm's reduction about 1/2, 1, 3/2 or infinity by one
    division, then its polynomial."""
    a, b, c, d = t < 0.4375, t < 0.6875, t < 1.1875, t < 2.4375
    num = t if a else (2.0 * t - 1.0 if b else (t - 1.0 if c else (t - 1.5 if d else -1.0)))
    den = 1.0 if a else (2.0 + t if b else (t + 1.0 if c else (1.0 + 1.5 * t if d else t)))
    x = num / den
    hi = 0.0 if a else (_ATAN_HI[0] if b else (_ATAN_HI[1] if c else (_ATAN_HI[2] if d else _ATAN_HI[3])))
    lo = 0.0 if a else (_ATAN_LO[0] if b else (_ATAN_LO[1] if c else (_ATAN_LO[2] if d else _ATAN_LO[3])))
    z = x * x
    w = z * z
    s1 = z * (_ATAN[0] + w * (_ATAN[2] + w * (_ATAN[4] + w * (_ATAN[6] + w * (_ATAN[8] + w * _ATAN[10])))))
    s2 = w * (_ATAN[1] + w * (_ATAN[3] + w * (_ATAN[5] + w * (_ATAN[7] + w * _ATAN[9]))))
    return x - x * (s1 + s2) if a else hi - ((x * (s1 + s2) - lo) - x)
