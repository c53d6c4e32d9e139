"""Run-time visibility of receiver vertices and direct illumination in SH (Zhou et al. 2005, Sec. 4).

Visibility pass
    The visibility of a receiver vertex is its self-visibility times the
    occlusion fields of the other objects, looked up at the vertex
    (:meth:`OcclusionField.lookup`, rotated with each object's pose), in order
    of increasing distance between the objects' bounding-sphere centres and the
    receiver's (Iwasaki et al. Sec. 6.1), each product truncated to order n::

        V_j = P_n( ... P_n( P_n(V_self,j O_1(x_j)) O_2(x_j) ) ... )

    (:func:`prtlab.sh.product`). The truncation after each product is the
    shadow-field approximation; its cost on the shading is measured in the tests.

Direct pass (Eq. 7-8 of Iwasaki et al. with the separable BRDF of the receiver)::

    B(x_j, w_o) = sum_k h_k(w_o) colour_k int L(w) V_j(w) g_k(w) max(0, n_j . w) dw
               = sum_k h_k(w_o) colour_k < L_j , P_n(V_j G_jk) >

with ``G_jk`` the SH of ``g_k cos`` (:func:`prtlab.brdf.project_g_cos`) and
``L_j`` the SH of the incident radiance (the environment, the same for every
vertex, or a source radiance field looked up at the vertex). Since ``L_j``
has order n, ``<L, P_n(V G)>`` is exactly the triple integral of the three
order-n functions (:func:`prtlab.sh.triple_integral`): no truncation beyond
that of the functions themselves.

References
----------
K. Zhou et al., "Precomputed shadow fields for dynamic scenes", SIGGRAPH 2005, Sec. 4.
K. Iwasaki et al., EGSR 2007, Eq. (5)-(8), Sec. 6.1 (sorting occluders by distance).
"""

from __future__ import annotations

import numba
import numpy as np

from prtlab import sh

__all__ = ["occluder_order", "visibility_pass", "direct_pass"]


def occluder_order(receiver_center, occluder_centers) -> np.ndarray:
    """Indices of the occluders by increasing distance of their centres from the receiver's centre."""
    c = np.asarray(receiver_center, dtype=np.float64)
    oc = np.asarray(occluder_centers, dtype=np.float64).reshape(-1, 3)
    return np.argsort(np.linalg.norm(oc - c, axis=1), kind="stable")


def visibility_pass(self_visibility, occluder_visibility, method: str = "sparse") -> np.ndarray:
    """Product of a vertex's self-visibility with the other objects' occlusion, truncated after each factor.

    Parameters
    ----------
    self_visibility : (V, n*n) float
        World-frame SH of the self-visibility of every vertex.
    occluder_visibility : sequence of (V, n*n) float
        The occlusion of each other object at the vertices (world frame), in
        the order the products are taken (nearest first, :func:`occluder_order`).
    method : {"sparse", "dense"}
        Tier of :func:`prtlab.sh.product`.

    Returns
    -------
    visibility : (V, n*n) float64
    """
    v = np.asarray(self_visibility, dtype=np.float64)
    if v.ndim != 2:
        raise ValueError(f"self_visibility must be (V, n*n), got shape {v.shape}")
    order = int(round(np.sqrt(v.shape[1])))
    for i, o in enumerate(occluder_visibility):
        o = np.asarray(o, dtype=np.float64)
        if o.shape != v.shape:
            raise ValueError(f"occluder_visibility[{i}] must be {v.shape} like self_visibility, got {o.shape}")
        if len(v):
            v = sh.product(v, o, order, method=method, channels=False)
    return v


@numba.njit(cache=True, parallel=True)
def _direct_kernel(transfer, light, h, colour, out):
    """out[v, c] = sum_k h[v, k] colour[k, c] sum_i transfer[v, k, i] light[v, i, c]."""
    n_v, n_k, n2 = transfer.shape
    n_c = colour.shape[1]
    for v in numba.prange(n_v):
        for c in range(n_c):
            acc = 0.0
            for k in range(n_k):
                dot = 0.0
                for i in range(n2):
                    dot += transfer[v, k, i] * light[v, i, c]
                acc += h[v, k] * colour[k, c] * dot
            out[v, c] = acc


def direct_pass(light, visibility, g_cos, h, colour, method: str = "numba") -> np.ndarray:
    """Direct illumination per vertex: ``sum_k h_k colour_k int L V g_k cos`` (Iwasaki et al. Eq. 7-8).

    Parameters
    ----------
    light : (n*n, C) or (V, n*n, C) float
        SH of the incident radiance: one environment for all vertices, or per vertex.
    visibility : (V, n*n) float
        From :func:`visibility_pass`.
    g_cos : (V, K, n*n) float
        SH of ``g_k(w) max(0, n . w)`` per vertex (:func:`prtlab.brdf.project_g_cos`).
    h : (V, K) float
        ``h_k(w_o)`` toward the viewer (:func:`prtlab.brdf.project_h`).
    colour : (K, C) float
        Per-channel weights of the terms (``SeparableBRDF.colour``).
    method : {"numba", "reference"}
        ``"numba"``: truncated products ``P_n(V G_k)`` then a parallel dot
        kernel. ``"reference"``: the dense Gaunt tensor contracted with the
        three functions (the triple integral, :func:`prtlab.sh.gaunt_tensor`).

    Returns
    -------
    radiance : (V, C) float64
    """
    visibility = np.asarray(visibility, dtype=np.float64)
    g_cos = np.asarray(g_cos, dtype=np.float64)
    h = np.asarray(h, dtype=np.float64)
    colour = np.asarray(colour, dtype=np.float64)
    light = np.asarray(light, dtype=np.float64)
    if visibility.ndim != 2:
        raise ValueError(f"visibility must be (V, n*n), got shape {visibility.shape}")
    n_v, n2 = visibility.shape
    order = int(round(np.sqrt(n2)))
    if order * order != n2:
        raise ValueError(f"visibility must have n*n coefficients, got {n2}")
    if g_cos.ndim != 3 or g_cos.shape[0] != n_v or g_cos.shape[2] != n2:
        raise ValueError(f"g_cos must be (V, K, n*n) = ({n_v}, K, {n2}), got shape {g_cos.shape}")
    n_k = g_cos.shape[1]
    if h.shape != (n_v, n_k):
        raise ValueError(f"h must be (V, K) = ({n_v}, {n_k}), got shape {h.shape}")
    if colour.ndim != 2 or colour.shape[0] != n_k:
        raise ValueError(f"colour must be (K, C) with K = {n_k}, got shape {colour.shape}")
    n_c = colour.shape[1]
    if light.shape == (n2, n_c):
        light = np.broadcast_to(light, (n_v, n2, n_c))
    elif light.shape != (n_v, n2, n_c):
        raise ValueError(f"light must be (n*n, C) = ({n2}, {n_c}) or (V, n*n, C), got shape {light.shape}")
    for name, arr in (("light", light), ("visibility", visibility), ("g_cos", g_cos), ("h", h)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains NaN or inf")
    if method not in ("numba", "reference"):
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
    if n_v == 0:
        return np.zeros((0, n_c))
    if method == "reference":
        gaunt = sh.gaunt_tensor(order).dense()  # int Y_a Y_b Y_c
        tri = np.einsum("abc,vax,vb,vkc->vkx", gaunt, light, visibility, g_cos)  # (V, K, C)
        return np.einsum("vk,kc,vkc->vc", h, colour, tri)
    transfer = sh.product(np.broadcast_to(visibility[:, None, :], g_cos.shape), g_cos, order, channels=False)
    out = np.empty((n_v, n_c))
    _direct_kernel(np.ascontiguousarray(transfer), np.ascontiguousarray(light), np.ascontiguousarray(h),
                   np.ascontiguousarray(colour), out)
    return out
