"""Haar wavelet triple products and products (Ng, Ramamoorthi, Hanrahan 2004).

Measure. A face is the unit square ``[0, 1]^2`` of its parameter domain, as in
Ng et al. 2004; the cube is the union of six such squares (total area 6). A
coefficient array ``a = haar2d(x)`` codes the piecewise-constant function equal
to ``x[i, j]`` on texel ``(i, j)``; in the continuous orthonormal Haar basis of
the unit square its coefficients are ``alpha = a / r`` (see :func:`haar2d`). So::

    triple_product(haar2d(x), haar2d(y), haar2d(z)) = sum_{f,i,j} x y z / r**2
                                                   = int_cube f g h dA.

The solid-angle integral ``int_S2 f g h dw ~ sum x y z omega`` is the same
call with the texel solid angles folded into one factor
(``measure="solid_angle"``, which multiplies ``ihaar2d(a)`` by
``omega * r**2`` before the parameter-domain product).

Tripling coefficients ``C_ijk = int Psi_i Psi_j Psi_k`` of the 2D Haar basis on
the unit square (scaling ``phi = 1``; wavelet of type t at node S of level l
equal to ``2**l s_t`` on S) are non-zero only when

1. all three are the scaling function: ``C = 1``;
2. two are the same wavelet ``psi_S`` and the third is the scaling function or
   a wavelet of a coarser node whose support contains S: ``C = Psi_k|S``, the
   (constant) value of the third function on S (1, or ``+-2**l_k``);
3. the three are the three distinct wavelet types of one node S:
   ``C = 2**l`` (the sign patterns multiply to +1).

Summing rule 2 over the ancestors of each coefficient is, for every node, the
product with the mean of the third function over that node; those means are
carried down the quadtree in one pass, so a triple product costs O(N) for N
coefficients (the ancestor sums of Ng et al. cost O(N log N)), never the
dense O(N^3) tensor.
"""

from __future__ import annotations

import numpy as np

from ..geometry._spheremaps import cubemap_solid_angles
from . import _kernels
from ._haar import _as_cubemaps, _check_finite, _check_method, _forward_reference, _inverse_reference, _kernel_array

__all__ = ["triple_product", "product"]

_MEASURES = ("parameter", "solid_angle")


def _prepare(arrays, names, per_face: bool, check_finite: bool):
    hint = "" if per_face else "; pass per_face=True for single (..., r, r) faces"
    coerced = [
        _as_cubemaps(x, n, faces_axis=not per_face, hint=hint, check_finite=check_finite)
        for x, n in zip(arrays, names)
    ]
    shapes = {x.shape[-1] for x in coerced}
    if len(shapes) != 1:
        raise ValueError(
            f"{', '.join(names)} must share one face resolution, got r = "
            f"{', '.join(str(x.shape[-1]) for x in coerced)}; resample them to one resolution"
        )
    core = coerced[0].shape[-3:] if not per_face else coerced[0].shape[-2:]
    try:
        batch = np.broadcast_shapes(*[x.shape[: -len(core)] for x in coerced])
    except ValueError:
        raise ValueError(
            f"the batch axes of {', '.join(names)} "
            f"({', '.join(str(x.shape[: -len(core)]) for x in coerced)}) do not broadcast"
        ) from None
    r = coerced[0].shape[-1]
    flats = [
        _kernel_array((x if x.shape == batch + core else np.broadcast_to(x, batch + core)).reshape(-1, r, r))
        for x in coerced
    ]
    return flats, batch, core, r


def _post_check(values: np.ndarray, flats, names) -> None:
    """The kernels' outputs are non-finite iff an input is (every coefficient enters a product that
    reaches the result): check the cheap output, and explain from the inputs only if it fails."""
    if not np.all(np.isfinite(values)):
        for flat, name in zip(flats, names):
            _check_finite(flat, name)
        raise ValueError(f"{', '.join(names)} are too large: their products overflow float64; rescale them")


def _check_measure(measure) -> str:
    if measure not in _MEASURES:
        raise ValueError(f"measure must be one of {', '.join(repr(m) for m in _MEASURES)}, got {measure!r}")
    return measure


def _fold_solid_angle(flat: np.ndarray, r: int, method: str) -> np.ndarray:
    """Haar coefficients of ``ihaar2d(a) * omega * r**2`` for flat faces in cube order."""
    weight = cubemap_solid_angles(r)[0] * (r * r)  # the same texel pattern on every face
    if method == "reference":
        return _forward_reference(_inverse_reference(flat) * weight)
    texels = np.empty_like(flat)
    out = np.empty_like(flat)
    if flat.shape[0]:
        _kernels.haar_inverse(flat, texels)
        _kernels.haar_forward(texels * weight, out)
    return out


def triple_product(a, b, c, method: str = "numba", measure: str = "parameter", per_face: bool = False):
    """Integral of the product of three Haar-coded cubemaps.

    Parameters
    ----------
    a, b, c : (..., 6, r, r) float, or (..., r, r) with ``per_face=True``
        Coefficients from :func:`haar2d`; batch axes broadcast.
    method : {"numba", "reference"}
        ``"numba"``: the tripling-coefficient rules of Ng et al. 2004 in one
        quadtree pass per face (O(N)). ``"reference"``: reconstruct the texels
        with the reference inverse transform, multiply, sum (brute force).
    measure : {"parameter", "solid_angle"}
        ``"parameter"``: each face is the unit square ``[0, 1]^2`` (Ng et al.);
        ``"solid_angle"``: the integral over the sphere, texels weighted by
        their exact solid angle.
    per_face : bool
        If True, the trailing ``(r, r)`` axes are one face and the result is
        that face's integral; the leading axes are all batch axes.
        (Colour: put the channel axis in front, ``np.moveaxis(a, -1, 0)``;
        batch axes broadcast, so a grey visibility multiplies RGB lighting.)

    Returns
    -------
    integral : (...) float64
        ``parameter``: ``sum_texels x y z / r**2`` with ``x = ihaar2d(a)``, ...;
        ``solid_angle``: ``sum_texels x y z omega``.

    Notes
    -----
    With ``alpha = a / r`` the continuous coefficients (see the module notes),
    per face::

        int f g h = alpha_0 beta_0 gamma_0
                  + sum_S sum_t (alpha_t beta_t G_S + alpha_t gamma_t B_S + beta_t gamma_t A_S)
                  + sum_S 2**l(S) sum_{(t1, t2, t3) permutations of the 3 types} alpha_t1 beta_t2 gamma_t3

    with ``A_S`` the mean of f over node S (the sum of its scaling and
    ancestor terms, rule 2), and so on. ``measure="solid_angle"`` folds
    ``omega r**2`` into ``a``.

    References
    ----------
    R. Ng, R. Ramamoorthi, P. Hanrahan, "Triple product wavelet integrals for
    all-frequency relighting", SIGGRAPH 2004, Section 4 (tripling coefficient
    theorem, cases 1-3) and Section 5 (sublinear-time evaluation by summing
    over each coefficient's parents).

    Examples
    --------
    >>> import numpy as np
    >>> from prtlab.wavelet import haar2d, triple_product
    >>> rng = np.random.default_rng(0)
    >>> x, y, z = rng.random((3, 6, 8, 8))
    >>> t = triple_product(haar2d(x), haar2d(y), haar2d(z))
    >>> bool(np.isclose(t, (x * y * z).sum() / 64))
    True
    """
    method = _check_method(method)
    measure = _check_measure(measure)
    (fa, fb, fc), batch, core, r = _prepare((a, b, c), ("a", "b", "c"), per_face, method == "reference")
    if measure == "solid_angle":
        if per_face:
            raise ValueError(
                "measure='solid_angle' needs whole cubemaps (..., 6, r, r) so each face's texel solid "
                "angles are known; use per_face=False"
            )
        fa = _fold_solid_angle(fa, r, method)
    if method == "reference":
        values = (_inverse_reference(fa) * _inverse_reference(fb) * _inverse_reference(fc)).sum(axis=(-2, -1)) / (r * r)
    else:
        values = np.empty(fa.shape[0])
        if fa.shape[0]:
            _kernels.haar_triple(fa, fb, fc, values)
        _post_check(values, (fa, fb, fc), ("a", "b", "c"))
    values = values.reshape(batch + core[:-2])
    return values if per_face else values.sum(axis=-1)


def product(a, b, method: str = "numba", per_face: bool = False) -> np.ndarray:
    """Haar coefficients of the product of two Haar-coded cubemaps.

    Parameters
    ----------
    a, b : (..., 6, r, r) float, or (..., r, r) with ``per_face=True``
        Coefficients from :func:`haar2d`; batch axes broadcast.
    method : {"numba", "reference"}
        ``"numba"``: ``(ab)_k = sum_ij C_ijk a_i b_j`` by the tripling rules
        in two quadtree passes (O(N)). ``"reference"``: reconstruct, multiply
        texel by texel, transform back (reference tiers of the transforms).
    per_face : bool
        As in :func:`triple_product`.

    Returns
    -------
    coeffs : broadcast shape, float64
        ``haar2d(ihaar2d(a) * ihaar2d(b))``: the product of two piecewise-constant
        functions is piecewise constant on the same texels, so the projection
        back to the Haar basis is exact; multiplying visibilities this way
        needs no transform.

    Notes
    -----
    Per face, in continuous coefficients (``alpha = a / r``; the result is
    returned times ``r``), for the wavelet of type t at node S of level l,
    with t1, t2 the other two types and ``E_D`` the sum of
    ``alpha_w beta_w`` over the wavelets w in the subtree of node D::

        (fg)_t,S = alpha_t B_S + beta_t A_S + 2**l (alpha_t1 beta_t2 + alpha_t2 beta_t1)
                 + 2**l sum_{quadrants Q of S} s_t(Q) E_child(Q)
        (fg)_0   = alpha_0 beta_0 + sum_w alpha_w beta_w

    References
    ----------
    R. Ng, R. Ramamoorthi, P. Hanrahan, "Triple product wavelet integrals for
    all-frequency relighting", SIGGRAPH 2004, Sections 4-5 (the product of
    two wavelet-coded functions is the tripling tensor contracted twice).
    """
    method = _check_method(method)
    (fa, fb), batch, core, r = _prepare((a, b), ("a", "b"), per_face, method == "reference")
    if method == "reference":
        out = _forward_reference(_inverse_reference(fa) * _inverse_reference(fb))
    else:
        out = np.empty_like(fa)
        if fa.shape[0]:
            _kernels.haar_product(fa, fb, out)
        _post_check(out[:, 0, 0], (fa, fb), ("a", "b"))
    return out.reshape(batch + core)


# --------------------------------------------------------------------------- tripling coefficients


def _basis_node(index: tuple[int, int], res: int):
    """(level, p, q, type) of the coefficient at ``index`` in the haar2d layout; level -1 = scaling."""
    i, j = index
    if i == 0 and j == 0:
        return -1, 0, 0, ""
    h = 1
    while max(i, j) >= 2 * h:
        h *= 2
    if i < h:
        return int(np.log2(h)), i, j - h, "01"
    if j < h:
        return int(np.log2(h)), i - h, j, "10"
    return int(np.log2(h)), i - h, j - h, "11"


def _basis_value_on(node, level: int, p: int, q: int) -> float:
    """Value of the continuous basis function ``node`` on the square (level, p, q) it contains, or 0."""
    lk, pk, qk, tk = node
    if lk == -1:
        return 1.0
    shift = level - lk
    if shift <= 0 or (p >> shift) != pk or (q >> shift) != qk:
        return 0.0
    di = (p >> (shift - 1)) & 1
    dj = (q >> (shift - 1)) & 1
    sign = {"01": (-1) ** dj, "10": (-1) ** di, "11": (-1) ** (di + dj)}[tk]
    return float(sign * 2**lk)


def tripling_coefficient(i: tuple[int, int], j: tuple[int, int], k: tuple[int, int], res: int) -> float:
    """``int_[0,1]^2 Psi_i Psi_j Psi_k`` by the rules of Ng et al. 2004 (continuous orthonormal basis).

    ``i, j, k`` are ``(row, column)`` positions in the :func:`haar2d` layout of
    an ``(res, res)`` face. Slow and obvious (one Python call per entry): the
    specification the quadtree kernels are tested against.
    """
    nodes = [_basis_node(x, res) for x in (i, j, k)]
    levels = [n[0] for n in nodes]
    if all(lv == -1 for lv in levels):
        return 1.0  # rule 1
    # rule 3: the three distinct types of one node
    if len({n[:3] for n in nodes}) == 1 and sorted(n[3] for n in nodes) == ["01", "10", "11"]:
        return float(2 ** levels[0])
    # rule 2: two identical wavelets and a coarser (or scaling) third
    for a, b, c in ((0, 1, 2), (0, 2, 1), (1, 2, 0)):
        if nodes[a] == nodes[b] and levels[a] >= 0 and levels[c] < levels[a]:
            return _basis_value_on(nodes[c], levels[a], nodes[a][1], nodes[a][2])
    return 0.0
