"""The validators every public function shares: integers, SH orders, directions, points, choices.

One place decides what the project accepts, so every entry point answers bad input the same
way: a ``TypeError`` when the value has the wrong type (``True`` is not an int here), a
``ValueError`` when it has the right type but is out of range, both naming the parameter,
what it must be, and what was given.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["check_int", "check_float", "check_bool", "check_order", "check_choice", "as_directions", "as_points"]


def check_int(value: Any, name: str, minimum: int | None = None, maximum: int | None = None,
              meaning: str = "") -> int:
    """``value`` as a Python int, checked to lie in ``[minimum, maximum]``.

    ``meaning`` (e.g. ``"number of SH bands"``) is added to the message in brackets.
    """
    bounds = []
    if minimum is not None:
        bounds.append(f">= {minimum}")
    if maximum is not None:
        bounds.append(f"<= {maximum}")
    what = f"{name} must be an int" + (" " + " and ".join(bounds) if bounds else "")
    what += f" ({meaning})" if meaning else ""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{what}, got {value!r} of type {type(value).__name__}")
    if (minimum is not None and value < minimum) or (maximum is not None and value > maximum):
        raise ValueError(f"{what}, got {value!r}")
    return int(value)


def check_float(value: Any, name: str, minimum: float | None = None, maximum: float | None = None, *,
                min_open: bool = False, max_open: bool = False, meaning: str = "") -> float:
    """``value`` (an int or a float, not a bool) as a finite Python float in the given range.

    ``min_open`` / ``max_open`` exclude the bound itself (``(0, 1]`` is ``minimum=0, min_open=True,
    maximum=1``); ``meaning`` is added to the message in brackets.
    """
    bounds = []
    if minimum is not None:
        bounds.append(f"{'>' if min_open else '>='} {minimum}")
    if maximum is not None:
        bounds.append(f"{'<' if max_open else '<='} {maximum}")
    what = f"{name} must be a finite number" + (" " + " and ".join(bounds) if bounds else "")
    what += f" ({meaning})" if meaning else ""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{what}, got {value!r} of type {type(value).__name__}")
    x = float(value)
    if (not np.isfinite(x) or (minimum is not None and (x <= minimum if min_open else x < minimum))
            or (maximum is not None and (x >= maximum if max_open else x > maximum))):
        raise ValueError(f"{what}, got {value!r}")
    return x


def check_bool(value: Any, name: str) -> bool:
    """``value`` if it is ``True`` or ``False`` (a NumPy bool too), else a TypeError (``1`` is not a bool)."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False, got {value!r} of type {type(value).__name__}")
    return bool(value)


def check_order(order: Any, name: str = "order") -> int:
    """An SH order ``n >= 1`` (bands ``l = 0..n-1``, ``n**2`` coefficients)."""
    return check_int(order, name, 1, meaning=f"{name} n means SH bands l = 0..n-1")


def check_choice(value: Any, name: str, allowed) -> Any:
    """``value`` if it is one of ``allowed``, else a ValueError listing them."""
    try:
        ok = any(value == a and (type(value) is type(a) or isinstance(value, str) and isinstance(a, str))
                 for a in allowed)
    except (TypeError, ValueError):  # an array compared element-wise
        ok = False
    if not ok:
        raise ValueError(f"{name} must be one of {', '.join(repr(a) for a in allowed)}, got {value!r}")
    return value


def as_directions(dirs: Any, name: str = "dirs", normalize: bool = True) -> np.ndarray:
    """``dirs`` as finite float64 ``(..., 3)``; normalised (zero vectors refused) unless ``normalize=False``."""
    arr = np.asarray(dirs)
    if arr.dtype.kind not in "fiu":
        raise TypeError(f"{name} must be a real (..., 3) array of directions, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if arr.ndim == 0 or arr.shape[-1] != 3:
        raise ValueError(f"{name} must be a (..., 3) array of unit directions, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; every direction must be a finite unit vector")
    if not normalize:
        return arr
    length = np.linalg.norm(arr, axis=-1, keepdims=True)
    if np.any(length == 0.0):
        raise ValueError(f"{name} contains a zero vector; every direction must be a unit vector")
    return arr / length


def as_points(points: Any, name: str = "points", flat: bool = False) -> np.ndarray:
    """``points`` as finite float64 ``(..., 3)`` (``(V, 3)`` and C-contiguous with ``flat=True``)."""
    arr = np.asarray(points)
    if arr.dtype.kind not in "fiu":
        raise TypeError(f"{name} must be a real array of points, got dtype {arr.dtype}")
    shape = "(V, 3)" if flat else "(..., 3)"
    if arr.ndim == 0 or arr.shape[-1] != 3 or (flat and arr.ndim != 2):
        raise ValueError(f"{name} must be a {shape} array of points, got shape {arr.shape}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; pass finite coordinates")
    return arr
