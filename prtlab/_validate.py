"""The validators every public function shares: integers, floats, bools, SH orders, directions, points,
choices, and the memory a computation may allocate.

One place decides what the project accepts, so every entry point answers bad input the same
way: a ``TypeError`` when the value has the wrong type (``True`` is not an int here), a
``ValueError`` when it has the right type but is out of range, both naming the parameter,
what it must be, and what was given.
"""

from __future__ import annotations

import os
from typing import Any, Mapping, NamedTuple

import numpy as np

__all__ = ["check_int", "check_float", "check_bool", "check_order", "check_choice", "as_real_array", "as_directions", "as_points",
           "MemoryNeed", "memory_limit", "check_memory"]


def _requirement(name: str, kind: str, minimum, maximum, meaning: str, min_open: bool = False,
                 max_open: bool = False) -> str:
    """``"<name> must be <kind> >= minimum and <= maximum (meaning)"``, the head of a range error."""
    bounds = []
    if minimum is not None:
        bounds.append(f"{'>' if min_open else '>='} {minimum}")
    if maximum is not None:
        bounds.append(f"{'<' if max_open else '<='} {maximum}")
    what = f"{name} must be {kind}" + (" " + " and ".join(bounds) if bounds else "")
    return what + (f" ({meaning})" if meaning else "")


def check_int(value: Any, name: str, minimum: int | None = None, maximum: int | None = None,
              meaning: str = "") -> int:
    """``value`` as a Python int, checked to lie in ``[minimum, maximum]``.

    ``meaning`` (e.g. ``"number of SH bands"``) is added to the message in brackets.
    """
    what = _requirement(name, "an int", minimum, maximum, meaning)
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
    what = _requirement(name, "a finite number", minimum, maximum, meaning, min_open, max_open)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{what}, got {value!r} of type {type(value).__name__}")
    x = float(value)
    if (not np.isfinite(x) or (minimum is not None and (x <= minimum if min_open else x < minimum))
            or (maximum is not None and (x >= maximum if max_open else x > maximum))):
        raise ValueError(f"{what}, got {value!r}")
    return x


def as_real_array(value: Any, name: str, finite_hint: str = "") -> np.ndarray:
    """``value`` as a float64 array: TypeError unless bool, int or float, ValueError on NaN or inf.

    ``finite_hint`` follows the NaN message after a semicolon (what to pass instead).
    """
    arr = np.asarray(value)
    if arr.dtype.kind not in "bfiu":
        raise TypeError(f"{name} must be a real array, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf" + (f"; {finite_hint}" if finite_hint else ""))
    return arr


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


class MemoryNeed(NamedTuple):
    """One large allocation of a computation: what it is, its size and the options it grows with."""

    what: str
    nbytes: float
    options: tuple[str, ...]


_GB = float(1 << 30)


def _size(nbytes: float) -> str:
    value, unit = (nbytes / _GB, "GB") if nbytes >= 0.95 * _GB else (nbytes / (1 << 20), "MB")
    return f"{value:,.0f} {unit}" if value >= 100 else f"{value:.3g} {unit}"


def memory_limit() -> float | None:
    """Bytes a computation may allocate: ``$PRTLAB_MAX_MEMORY_GB`` if set, else the memory available now
    (``MemAvailable`` of ``/proc/meminfo``, else ``os.sysconf``); None where neither is known."""
    env = os.environ.get("PRTLAB_MAX_MEMORY_GB")
    if env is not None and env.strip():
        try:
            gb = float(env)
        except ValueError:
            gb = float("nan")
        if not (np.isfinite(gb) and gb > 0):
            raise ValueError(f"environment variable PRTLAB_MAX_MEMORY_GB must be a number of GB > 0, got {env!r}")
        return gb * _GB
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES")) * float(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def check_memory(method: str, options: Any, needs, context: str) -> None:
    """Refuse, before allocating, a computation whose ``needs`` (:class:`MemoryNeed`) exceed :func:`memory_limit`.

    One ValueError line names the options of the largest allocation first (with their values from
    ``options``, a dataclass or a mapping), the estimate, ``context`` (e.g. ``"2,191 vertices"``) and the
    limit, e.g. ``"portals: option order=8 with res=64 and bounces=40 needs ~31 GB for 2,191 vertices
    (limit 20 GB): lower order, res or bounces"``.
    """
    needs = [n for n in needs if n.nbytes > 0]
    total = float(sum(n.nbytes for n in needs))
    limit = memory_limit()
    if limit is None or total <= limit:
        return
    names: list[str] = []
    for need in sorted(needs, key=lambda n: -n.nbytes):
        if need.nbytes >= 0.1 * total:  # the allocations that matter
            names += [name for name in need.options if name not in names]
    names = names[:3]
    get = options.get if isinstance(options, Mapping) else lambda name: getattr(options, name)
    values = [f"{name}={get(name)!r}" for name in names]
    said = f"option {values[0]}" + (" with " + " and ".join(values[1:]) if len(values) > 1 else "")
    lower = names[0] if len(names) == 1 else ", ".join(names[:-1]) + f" or {names[-1]}"
    biggest = max(needs, key=lambda n: n.nbytes).what
    raise ValueError(f"{method}: {said} needs ~{_size(total)} for {context} (limit {_size(limit)}; mostly "
                     f"{biggest}): lower {lower} (or set PRTLAB_MAX_MEMORY_GB)")
