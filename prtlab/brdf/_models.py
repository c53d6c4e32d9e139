"""Lambert and normalised Phong BRDFs, and the local shading frame.

Both models are the ones of :class:`prtlab.scene.Material` and of the Monte
Carlo reference (:mod:`prtlab.reference`):

.. math::

    f(\\omega_i, \\omega_o) = \\frac{k_d}{\\pi}
        + k_s \\frac{e + 2}{2 \\pi} \\max(0, r \\cdot \\omega_o)^e,
    \\qquad r = 2 (n \\cdot \\omega_i) n - \\omega_i ,

Lambert being ``k_s = 0`` (``k_d`` = albedo). Directions point away from the
surface (``wi`` toward the light, ``wo`` toward the viewer).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prtlab._validate import as_directions, check_choice, check_int

from ..geometry import tangent_frame
from . import _kernels

__all__ = ["Lambert", "Phong", "lambert", "phong", "from_material", "local_frame", "to_local", "to_world"]

_METHODS = ("numba", "reference")


def _check_method(method) -> str:
    return check_choice(method, "method", _METHODS)


def _broadcast(arrays: dict[str, np.ndarray]) -> list[np.ndarray]:
    try:
        batch = np.broadcast_shapes(*(a.shape[:-1] for a in arrays.values()))
    except ValueError:
        shapes = ", ".join(f"{k} {v.shape}" for k, v in arrays.items())
        raise ValueError(f"the batch axes of {shapes} do not broadcast; pass matching (..., 3) arrays") from None
    return [np.broadcast_to(a, batch + (3,)) for a in arrays.values()]


# --------------------------------------------------------------------------- local frame


def local_frame(normal) -> np.ndarray:
    """Rotation matrices of the local shading frames.

    Parameters
    ----------
    normal : (..., 3) float
        Surface normals (normalised here).

    Returns
    -------
    R : (..., 3, 3) float64
        Proper rotations with columns ``(t, b, n)``: ``R @ e_z = n``, so
        ``local = R.T @ world`` and ``world = R @ local``.

    Notes
    -----
    ``(t, b)`` are the tangents of :func:`prtlab.geometry.tangent_frame`
    (Duff et al. 2017), the frame the Monte Carlo reference samples in. The
    local azimuth ``phi = atan2(w . b, w . t)`` is measured from ``t`` toward
    ``b``. Every isotropic BRDF is independent of this choice; a truncated
    separable approximation is too unless it splits an azimuthal
    ``cos(m phi) / sin(m phi)`` pair (see :class:`SeparableBRDF`).
    """
    n = as_directions(normal, "normal")
    t, b = tangent_frame(n)
    return np.stack([t, b, n], axis=-1)


def to_local(dirs, normal) -> np.ndarray:
    """World directions ``(..., 3)`` to the local frame of ``normal`` (z = normal); batch axes broadcast."""
    d = as_directions(dirs, "dirs")
    R = local_frame(normal)
    return np.einsum("...ji,...j->...i", R, d)


def to_world(dirs_local, normal) -> np.ndarray:
    """Local directions ``(..., 3)`` (z = normal) to world directions; the inverse of :func:`to_local`."""
    d = as_directions(dirs_local, "dirs_local")
    R = local_frame(normal)
    return np.einsum("...ij,...j->...i", R, d)


# --------------------------------------------------------------------------- models


def _as_reflectance(value, name: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiu":
        raise TypeError(f"{name} must be a real scalar or (C,) array of reflectances, got dtype {arr.dtype}")
    arr = np.atleast_1d(arr.astype(np.float64))
    if arr.ndim != 1 or arr.shape[0] < 1:
        raise ValueError(f"{name} must be a scalar or a (C,) array with C >= 1 channels, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; reflectances must be finite numbers in [0, 1]")
    if np.any(arr < 0.0) or np.any(arr > 1.0):
        raise ValueError(f"{name} must lie in [0, 1] in every channel, got {arr.tolist()}")
    return arr


@dataclass(frozen=True, eq=False)
class Phong:
    """Normalised Phong BRDF ``kd / pi + ks (e + 2) / (2 pi) max(0, r . wo)^e``.

    Build it with :func:`phong` (which validates). Attributes are ``kd``,
    ``ks`` (both ``(C,)`` float64) and ``exponent`` (float ``e >= 0``).
    """

    kd: np.ndarray
    ks: np.ndarray
    exponent: float

    @property
    def channels(self) -> int:
        """Number of colour channels C."""
        return int(self.kd.shape[0])

    def eval(self, wi, wo, normal=None, method: str = "numba") -> np.ndarray:
        """Evaluate the BRDF.

        Parameters
        ----------
        wi, wo : (..., 3) float
            Incident (toward the light) and outgoing (toward the viewer)
            directions, normalised here; batch axes broadcast.
        normal : (..., 3) float, optional
            Surface normals in the same frame; default ``+z`` (local frame).
        method : {"numba", "reference"}
            Parallel numba kernel or its float64 numpy specification.

        Returns
        -------
        f : (..., C) float64

        Notes
        -----
        Two-sided: the normal is flipped to the side of ``wo`` (``f`` uses only
        ``r``, which is the same for ``n`` and ``-n``); when ``wi`` lies strictly
        on the other side (``(n . wi)(n . wo) < 0``) nothing is reflected and
        ``f = 0`` (no transmission). The Monte Carlo reference shades the side
        of the vertex normal and uses ``wo`` as given even behind it; the two
        agree whenever ``wi`` and ``wo`` are on the normal's side.
        """
        method = _check_method(method)
        arrays = {"wi": as_directions(wi, "wi"), "wo": as_directions(wo, "wo")}
        arrays["normal"] = np.array([0.0, 0.0, 1.0]) if normal is None else as_directions(normal, "normal")
        wi_b, wo_b, n_b = _broadcast(arrays)
        batch = wi_b.shape[:-1]
        flat = [np.array(a.reshape(-1, 3), dtype=np.float64, order="C") for a in (wi_b, wo_b, n_b)]
        e = float(self.exponent)
        if method == "reference":
            out = _kernels.phong_eval_numpy(*flat, self.kd, self.ks, e)
        else:
            out = np.empty((flat[0].shape[0], self.channels))
            if out.shape[0]:
                _kernels.phong_eval_kernel(*flat, self.kd, self.ks, e, out)
        return out.reshape(batch + (self.channels,))

    def directional_albedo(self, cos_theta, n_nodes: int = 256) -> np.ndarray:
        """Directional albedo ``a(wi) = int_H f(wi, wo) cos(theta_o) dwo`` by quadrature.

        Parameters
        ----------
        cos_theta : (...,) float in (0, 1]
            Cosine of the incidence angle.
        n_nodes : int
            Gauss-Legendre nodes in ``theta_o`` (and ``2 n_nodes`` uniform
            nodes in azimuth); default 256, plenty for exponents <= 1000.

        Returns
        -------
        albedo : (..., C) float64
            ``kd + ks a_s(theta_i)`` with ``a_s(0) = 1`` exactly (the
            normalisation) and ``a_s < 1`` at oblique incidence, where part of
            the lobe falls below the horizon and ``cos(theta_o)`` is smaller
            than at the lobe's centre: normalised Phong loses energy there and
            never gains any when ``kd + ks <= 1``.
        """
        mu = np.asarray(cos_theta, dtype=np.float64)
        if not np.all(np.isfinite(mu)) or np.any(mu <= 0.0) or np.any(mu > 1.0):
            raise ValueError("cos_theta must lie in (0, 1]; directions at or below the horizon have no albedo")
        check_int(n_nodes, "n_nodes", 2)
        t, w = np.polynomial.legendre.leggauss(int(n_nodes))
        theta = 0.25 * np.pi * (t + 1.0)
        w_theta = 0.25 * np.pi * w * np.sin(theta) * np.cos(theta)
        n_phi = 2 * int(n_nodes)
        phi = 2.0 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
        st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
        wo = np.stack(np.broadcast_arrays(st * np.cos(phi), st * np.sin(phi), ct), axis=-1).reshape(-1, 3)
        weights = (w_theta[:, None] * np.full(n_phi, 2.0 * np.pi / n_phi)).ravel()
        flat = mu.reshape(-1)
        out = np.empty((flat.shape[0], self.channels))
        for i, c in enumerate(flat):
            wi = np.array([np.sqrt(max(0.0, 1.0 - c * c)), 0.0, c])
            out[i] = weights @ self.eval(wi, wo)
        return out.reshape(mu.shape + (self.channels,))


@dataclass(frozen=True, eq=False)
class Lambert(Phong):
    """Lambertian BRDF ``albedo / pi``: a :class:`Phong` with ``ks = 0``.

    Build it with :func:`lambert`.
    """

    @property
    def albedo(self) -> np.ndarray:
        """(C,) the albedo (= ``kd``)."""
        return self.kd


def phong(kd, ks, exponent) -> Phong:
    """Normalised Phong BRDF.

    Parameters
    ----------
    kd, ks : float or (C,) float in [0, 1]
        Diffuse and specular reflectance (broadcast to a common C); per
        channel ``kd + ks <= 1``.
    exponent : float >= 0
        Phong exponent ``e``.

    Returns
    -------
    Phong

    Notes
    -----
    ``f = kd / pi + ks (e + 2) / (2 pi) max(0, r . wo)^e``: at normal
    incidence the specular lobe reflects exactly ``ks`` of the incident
    energy (``(e + 2) / (2 pi) int_H cos^(e+1) = 1``), less elsewhere, so
    ``kd + ks <= 1`` is the condition that no direction gains energy.

    References
    ----------
    E. Lafortune, Y. Willems, "Using the modified Phong reflectance model
    for physically based rendering", Tech. Rep. CW197, KU Leuven, 1994.

    Examples
    --------
    >>> from prtlab.brdf import phong
    >>> b = phong(0.2, 0.5, 10)
    >>> b.eval([0, 0, 1], [0, 0, 1]).round(4)  # kd/pi + ks (e+2)/(2 pi)
    array([1.0186])
    >>> b.directional_albedo(1.0).round(12)  # exactly kd + ks at normal incidence
    array([0.7])
    """
    kd_arr = _as_reflectance(kd, "kd")
    ks_arr = _as_reflectance(ks, "ks")
    try:
        kd_arr, ks_arr = (np.array(a, dtype=np.float64) for a in np.broadcast_arrays(kd_arr, ks_arr))
    except ValueError:
        raise ValueError(
            f"kd has {kd_arr.shape[0]} channels and ks {ks_arr.shape[0]}; pass the same number (or a scalar)"
        ) from None
    if np.any(kd_arr + ks_arr > 1.0 + 1e-12):
        raise ValueError(
            f"kd + ks = {(kd_arr + ks_arr).tolist()} exceeds 1: the surface would reflect more energy than it "
            "receives (energy gain); scale kd and ks down so that kd + ks <= 1 in every channel"
        )
    if isinstance(exponent, bool) or not isinstance(exponent, (int, float, np.integer, np.floating)):
        raise TypeError(f"exponent must be a real number, got {type(exponent).__name__}")
    if not np.isfinite(exponent) or exponent < 0:
        raise ValueError(f"exponent must be a finite number >= 0 (the Phong exponent), got {exponent!r}")
    return Phong(kd=kd_arr, ks=ks_arr, exponent=float(exponent))


def lambert(albedo) -> Lambert:
    """Lambertian BRDF ``albedo / pi``.

    Parameters
    ----------
    albedo : float or (C,) float in [0, 1]

    Returns
    -------
    Lambert
        A :class:`Phong` with ``kd = albedo``, ``ks = 0``, ``exponent = 0``;
        its directional albedo is ``albedo`` for every incidence.
    """
    kd = _as_reflectance(albedo, "albedo")
    return Lambert(kd=kd, ks=np.zeros_like(kd), exponent=0.0)


def from_material(material) -> Phong:
    """The BRDF of a :class:`prtlab.scene.Material` (``diffuse`` -> :func:`lambert`, ``phong`` -> :func:`phong`)."""
    kind = getattr(material, "type", None)
    if kind == "diffuse":
        return lambert(material.albedo)
    if kind == "phong":
        return phong(material.kd, material.ks, material.exponent)
    raise ValueError(f"material must be a prtlab.scene.Material of type 'diffuse' or 'phong', got type {kind!r}")
