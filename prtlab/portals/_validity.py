"""The two validity criteria for dynamic exterior objects (Yue et al. 2009, Section 6)."""

from __future__ import annotations

import warnings

import numpy as np

__all__ = ["PortalValidityWarning", "check_shell_distance", "check_interior_solid_angle"]


class PortalValidityWarning(UserWarning):
    """An exterior object breaks an assumption of the shell approximation."""


def _positive(value, name):
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return value


def _holds(ok, message: str) -> bool:
    """``ok`` as a bool; a :class:`PortalValidityWarning` with ``message`` (at the caller's caller) if False."""
    if not ok:
        warnings.warn(message, PortalValidityWarning, stacklevel=3)
    return bool(ok)


def check_shell_distance(portal_size: float, distance: float, max_angle_deg: float = 5.0) -> bool:
    """First criterion: every portal point sees an exterior point ``q`` as its centre does.

    Holds when ``l / (2 r) < theta_M`` (``l`` the portal size, largest distance
    between two of its points; ``r`` the distance from ``q`` to the portal
    centre; ``theta_M`` the allowed directional error). Warns
    (:class:`PortalValidityWarning`) and returns False otherwise.

    Examples
    --------
    >>> check_shell_distance(0.5, 3.0)   # the paper's car window: 50 cm, objects beyond 3 m
    True
    """
    l = _positive(portal_size, "portal_size")
    r = _positive(distance, "distance")
    theta = np.radians(_positive(max_angle_deg, "max_angle_deg"))
    return _holds(l / (2.0 * r) < theta,
                  f"exterior object at {r:.3g} from a portal of size {l:.3g}: directional error l/(2r) = "
                  f"{np.degrees(l / (2 * r)):.2f} deg >= {np.degrees(theta):.2f} deg; split the portal into smaller "
                  "ones")


def check_interior_solid_angle(interior_area: float, distance: float, max_ratio: float = 0.02) -> bool:
    """Second criterion: an exterior object receives little light reflected by the interior.

    Holds when ``A / (4 pi d^2) < R_Theta`` (``A`` the interior area facing the
    object, ``d`` its distance). Warns and returns False otherwise.

    Examples
    --------
    >>> check_interior_solid_angle(2.0, 2.9)   # the paper's sedan: d > 2.8 m
    True
    """
    a = _positive(interior_area, "interior_area")
    d = _positive(distance, "distance")
    ratio = _positive(max_ratio, "max_ratio")
    value = a / (4.0 * np.pi * d * d)
    return _holds(value < ratio,
                  f"exterior object at {d:.3g} sees the interior (area {a:.3g}) under A/(4 pi d^2) = {value:.3g} >= "
                  f"{ratio:.3g}: light reflected from the interior onto it is not negligible")
