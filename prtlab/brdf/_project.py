"""SH projections a receiver vertex needs: ``g_k(wi) max(0, n . wi)`` per normal, ``h_k`` per view.

Iwasaki et al. (EGSR 2007, Eq. 11-13) write the reflected radiance as
``B(x, wo) = sum_k h_k(wo) int L(wi) V(wi) g_k(wi) (n . wi) dwi``: the
per-vertex SH vectors of ``g_k cos`` (precomputed, rotated with the object)
meet the SH vectors of incident radiance and visibility, and ``h_k`` is read
at the view direction.
"""

from __future__ import annotations

import numpy as np

from prtlab._validate import as_directions, check_order

from .. import sh
from ._models import _check_method, local_frame, to_local
from ._separable import SeparableBRDF

__all__ = ["project_g_cos", "project_h", "transfer_error"]


def _check_sep(sep) -> SeparableBRDF:
    if not isinstance(sep, SeparableBRDF):
        raise TypeError(f"sep must be a SeparableBRDF (from prtlab.brdf.separable), got {type(sep).__name__}")
    if sep.parameterisation != "plain":
        raise ValueError(
            "sep uses the 'reflection' parameterisation, whose h_k depends on wi as well as wo, so h_k cannot "
            "leave the integral over wi (Iwasaki et al. Eq. 7); build it with parameterisation='plain'"
        )
    return sep


def _local_samples(sep: SeparableBRDF, order: int):
    """Quadrature of the local hemisphere: directions (P, 3), weights (P,), values ``g_k cos`` (P, K).

    Polar: the separable grid's own Gauss-Legendre nodes (no interpolation).
    Azimuth: ``N = 2 (m_max + order) + 1`` uniform nodes, exact for every
    ``T(m phi) Y_lm'`` product (trigonometric degree ``< N``).
    """
    m_max = int(sep.freq.max()) if sep.K else 0
    n_phi = 2 * (m_max + order) + 1
    phi = 2.0 * np.pi * np.arange(n_phi) / n_phi
    theta = sep.theta_in
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    dirs = np.stack(np.broadcast_arrays(st * np.cos(phi), st * np.sin(phi), ct), axis=-1).reshape(-1, 3)
    weights = np.repeat(sep.weights_in * 2.0 * np.pi / n_phi, n_phi)
    angle = phi[:, None] * sep.freq[None, :]  # (N, K)
    trig = np.where(sep.parity[None, :] == 0, np.cos(angle), np.sin(angle))
    values = (sep.g_radial.T[:, None, :] * np.cos(theta)[:, None, None] * trig[None, :, :]).reshape(-1, sep.K)
    return dirs, weights, values


def project_g_cos(sep, normals, order: int, method: str = "numba") -> np.ndarray:
    """SH vectors of ``g_k(wi) max(0, n . wi)`` in the world frame, for many normals.

    Parameters
    ----------
    sep : SeparableBRDF
        A ``"plain"`` separable approximation.
    normals : (..., 3) float
        Unit surface normals (normalised here).
    order : int
        SH order n (bands ``l < n``).
    method : {"numba", "reference"}
        ``"numba"``: project once in the local frame and turn the vectors with
        :func:`prtlab.sh.rotate` by each :func:`local_frame` matrix.
        ``"reference"``: quadrature per normal with the world basis functions
        ``Y(R w_local)`` (memory ``normals x samples x n^2``).

    Returns
    -------
    coeffs : (..., K, n*n) float64
        ``c_k = int_S2 g_k(R^T w) max(0, n . w) Y(w) dw`` with ``R`` the local
        frame of ``n``. Multiply by ``sep.colour[k]`` for the channels.

    Notes
    -----
    ``g_k`` is defined in the local frame ``(t, b, n)`` of
    :func:`local_frame`, azimuth measured from ``t`` toward ``b``; the world
    function is ``w -> g_k(R^T w)``, whose coefficients are
    ``rotate(c_local, R)``. Use the same frame for :func:`project_h` (pass the
    same normals). For a Lambertian ``sep`` (one term, ``g = 1/pi``) this is
    ``zh_rotate(clamped_cosine_zh(n), normal) / pi``.

    References
    ----------
    K. Iwasaki et al., EGSR 2007, Eq. (13) (``g_k' cos`` as a coefficient vector,
    rotated with the object by SH rotation).
    """
    sep = _check_sep(sep)
    order = check_order(order)
    method = _check_method(method)
    n = as_directions(normals, "normals")
    batch = n.shape[:-1]
    flat = n.reshape(-1, 3)
    n_c = order * order
    if flat.shape[0] == 0:
        return np.zeros(batch + (sep.K, n_c))
    dirs, weights, values = _local_samples(sep, order)
    R = local_frame(flat)  # (V, 3, 3)
    if method == "numba":
        local = (values * weights[:, None]).T @ sh.basis(dirs, order)  # (K, n^2)
        out = sh.rotate(local[None, :, :], R[:, None, :, :], channels=False)
    else:
        world_dirs = np.einsum("vij,pj->vpi", R, dirs)
        y = sh.basis(world_dirs, order, method="reference")  # (V, P, n^2)
        out = np.einsum("pk,vpc->vkc", values * weights[:, None], y)
    return out.reshape(batch + (sep.K, n_c))


def project_h(sep, wo_dirs, normals=None, method: str = "numba") -> np.ndarray:
    """``h_k`` at view directions.

    Parameters
    ----------
    sep : SeparableBRDF
        A ``"plain"`` separable approximation.
    wo_dirs : (..., 3) float
        Outgoing directions (toward the viewer): local (z = normal) when
        ``normals`` is None, else world directions.
    normals : (..., 3) float, optional
        World normals (broadcast with ``wo_dirs``); the local frame is that of
        :func:`local_frame`, the one :func:`project_g_cos` uses.
    method : {"numba", "reference"}

    Returns
    -------
    h : (..., K) float64
        So that the reflected radiance is
        ``sum_k h_k(wo) colour[k] int L(wi) g_k(wi) max(0, n . wi) dwi``.
        Directions below the horizon get the horizon value (exact for the
        Lambertian term; :mod:`prtlab.reference` evaluates the Phong formula
        as given there).
    """
    sep = _check_sep(sep)
    local = as_directions(wo_dirs, "wo_dirs") if normals is None else to_local(wo_dirs, normals)
    return sep.h(local, method=method)


def _rotation_z(phi: np.ndarray) -> np.ndarray:
    c, s = np.cos(phi), np.sin(phi)
    R = np.zeros(phi.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def transfer_error(sep, order: int) -> np.ndarray:
    """Relative error of the separable BRDF as seen by order-n SH lighting.

    Parameters
    ----------
    sep : SeparableBRDF
        A ``"plain"`` separable approximation.
    order : int
        SH order n of the incident radiance.

    Returns
    -------
    error : (C,) float64
        ``sqrt(int_H ||T(wo) - T_K(wo)||^2 dwo / int_H ||T(wo)||^2 dwo)`` with
        ``T(wo) = int f(wi, wo) cos(theta_i) Y(wi) dwi`` (local frame, order n)
        and ``T_K(wo) = sum_k colour[k] h_k(wo) int g_k cos Y`` (what
        :func:`project_g_cos` and :func:`project_h` deliver). By Cauchy-Schwarz,
        the reflected radiance error for any order-n radiance ``L`` is at most
        ``||L|| ||T(wo) - T_K(wo)||``: this is the part of the BRDF error that
        low-frequency PRT can see.

    Notes
    -----
    Computed on the separable grid itself (its polar nodes for ``wi`` and
    ``wo``, its uniform azimuths for ``wi``), so it measures the truncation to
    K terms only and is 0 at full rank. The exact ``T`` is isotropic:
    ``T(R_z wo) = rotate(T(wo), R_z)``, so it is computed at ``phi_o = 0`` and
    turned; ``T_K`` is evaluated at every azimuth (it need not be isotropic).
    """
    from ._separable import _tables

    sep = _check_sep(sep)
    order = check_order(order)
    n_theta, n_phi = sep.resolution
    _, w_i, theta_o, w_o, diffuse, lobe = _tables(sep.brdf.exponent, n_theta, n_phi, "plain")
    theta_i = sep.theta_in
    phi = 2.0 * np.pi * np.arange(n_phi) / n_phi
    st, ct = np.sin(theta_i)[:, None], np.cos(theta_i)[:, None]
    wi = np.stack(np.broadcast_arrays(st * np.cos(phi), st * np.sin(phi), ct), axis=-1)  # (n_i, N, 3)
    y = sh.basis(wi, order)  # (n_i, N, n^2)
    weight = (w_i * np.cos(theta_i))[:, None] * (2.0 * np.pi / n_phi)
    # T at phi_o = 0: f(wi, wo) with phi_o - phi_i = -phi_s, f even in the difference
    t_d = np.einsum("is,ios,isc->oc", weight, diffuse, y)
    t_l = np.einsum("is,ios,isc->oc", weight, lobe, y)
    kd, ks = sep.brdf.kd, sep.brdf.ks
    t0 = kd[:, None, None] * t_d[None] + ks[:, None, None] * t_l[None]  # (C, n_o, n^2)
    m_max = int(sep.freq.max()) if sep.K else 0
    n_phi_o = 2 * (m_max + order) + 1
    phi_o = 2.0 * np.pi * np.arange(n_phi_o) / n_phi_o
    R = _rotation_z(phi_o)  # (P, 3, 3)
    t_full = sh.rotate(t0[:, :, None, :], R[None, None], channels=False)  # (C, n_o, P, n^2)
    dirs, weights, values = _local_samples(sep, order)
    c_local = (values * weights[:, None]).T @ sh.basis(dirs, order)  # (K, n^2)
    angle = phi_o[:, None] * sep.freq[None, :]
    trig = np.where(sep.parity[None, :] == 0, np.cos(angle), np.sin(angle))  # (P, K)
    h = sep.h_radial.T[:, None, :] * trig[None, :, :]  # (n_o, P, K)
    t_k = np.einsum("opk,kc,kl->copl", h, sep.colour, c_local)
    quad = w_o[:, None] * np.full(n_phi_o, 2.0 * np.pi / n_phi_o)[None, :]
    num = np.einsum("op,copl->c", quad, (t_full - t_k) ** 2)
    den = np.einsum("op,copl->c", quad, t_full**2)
    return np.where(den > 0, np.sqrt(num / np.where(den > 0, den, 1.0)), 0.0)
