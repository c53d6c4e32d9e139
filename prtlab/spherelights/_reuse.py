"""The geometry-only results of a frame kept for the next one while their inputs stay the same.

Much of a spherical-lights frame with the ground's rays (``ground_shading="rays"``) and the meshes' direct light
(``mesh_blockers``) is geometry: which ray from a ground point meets which face where, which rays of an object's
receivers are blocked. It does not change when only the lighting (the environment) does. A :class:`FrameReuse`
keeps each such result with a copy of every input it was computed from and hands it back only when the new inputs
equal the kept ones exactly (same type, shape, dtype and bytes: never a digest), so a moved, turned, scaled or
deformed object, a moved ground or light, or another option computes afresh, unless the caller gives an update: a
function of the kept inputs and result that computes the new result from the kept one (the ground's rays of the
objects that did not move kept, ``_groundrays.ground_hits_update``; likewise the objects' visible rays,
``ground_light``'s samples and the near blockers' caps: ``_meshdirect.mesh_direct_visible_update``,
``_ground.ground_samples_update``, ``_nearcaps.near_blocker_visibility_update``), exactly as a fresh computation
would.
"""

from __future__ import annotations

import numpy as np

__all__ = ["FrameReuse", "kept_by_key", "same_inputs"]


class FrameReuse:
    """One result per name, kept with the inputs it was computed from.

    ``get(name, inputs, compute, update=None)`` returns the kept result when ``inputs`` equal the kept inputs
    exactly; else ``update(kept_inputs, kept_result)`` if given and a result is kept: ``(result, counts)`` (then
    kept, with a copy of ``inputs``; ``counts`` a dict of what it kept and redid) or None; else ``compute()`` (then
    kept likewise). An update must give what ``compute()`` would, bit for bit. ``inputs``: nested tuples and lists
    of arrays, numbers, strings and None; arrays are compared by dtype, shape and bytes (so ``-0.0`` differs from
    ``0.0``, as it may change a result; a NaN equals the same NaN); other objects by ``==``. Between
    :meth:`start_frame` and :meth:`end_frame` the names asked for are counted, and ``end_frame`` forgets the results
    no call asked for (a frame keeps only what the frame before it computed, updated or reused). Two threads may
    call :meth:`get` at once for different names."""

    def __init__(self):
        self._kept: dict = {}
        self._computed: list = []
        self._reused: list = []
        self._updated: list = []

    def get(self, name, inputs, compute, update=None):
        kept = self._kept.get(name)
        if kept is not None and _same(kept[0], inputs):
            self._reused.append(name)
            return kept[1]
        if kept is not None and update is not None:
            updated = update(kept[0], kept[1])
            if updated is not None:
                value, counts = updated
                self._kept[name] = (_copy(inputs), value)
                self._updated.append((name, counts))
                return value
        self._kept.pop(name, None)  # the old result goes before the new one is computed (peak memory)
        value = compute()
        self._kept[name] = (_copy(inputs), value)
        self._computed.append(name)
        return value

    def holds(self, name) -> bool:
        """Whether a result is kept under ``name`` (the next :meth:`get` may reuse or update it)."""
        return name in self._kept

    def clear(self) -> None:
        """Forget every kept result (the next frame computes everything)."""
        self._kept.clear()

    def start_frame(self) -> None:
        """Start counting the names asked for."""
        self._computed.clear()
        self._reused.clear()
        self._updated.clear()

    def end_frame(self) -> dict:
        """Forget the results not asked for since :meth:`start_frame`; returns ``{"computed": [...], "reused":
        [...], "updated": [(name, counts), ...]}``, the names asked for (``updated``: partly reused)."""
        used = set(self._computed) | set(self._reused) | {name for name, _ in self._updated}
        for name in [k for k in self._kept if k not in used]:
            del self._kept[name]
        return {"computed": list(self._computed), "reused": list(self._reused), "updated": list(self._updated)}


def kept_by_key(cache: dict, key, make, size: int = 4):
    """``cache[key]``, else ``make()`` made read-only and kept under ``key``, the oldest entries dropped past
    ``size``: the last few results of a function of small inputs, keyed by their bytes."""
    value = cache.get(key)
    if value is None:
        value = make()
        value.setflags(write=False)
        for old in list(cache)[: max(0, len(cache) - size + 1)]:
            cache.pop(old, None)
        cache[key] = value
    return value


def same_inputs(a, b) -> bool:
    """Whether ``a`` and ``b`` are equal as :class:`FrameReuse` compares inputs (exactly)."""
    return _same(a, b)


def _copy(x):
    """``x`` with every array copied (a caller changing its array in place must not change the kept inputs)."""
    if isinstance(x, (tuple, list)):
        return type(x)(_copy(v) for v in x)
    if isinstance(x, np.ndarray):
        return x.copy()
    return x


def _same(a, b) -> bool:
    """Exact equality of nested inputs: arrays by dtype, shape and bytes, other values by type and ``==``
    (floats by their bits)."""
    if isinstance(a, (tuple, list)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape and _same_bytes(a, b)
    if isinstance(a, float) or isinstance(b, float):
        return type(a) is type(b) and np.float64(a).tobytes() == np.float64(b).tobytes()
    return type(a) is type(b) and a == b


#: Arrays of at least this many bytes are compared as unsigned integers of their item size, not as ``bytes``
#: objects (a copy of each: 10 ms for two 8 MB arrays, against 0.24 ms compared in place).
_COMPARE_IN_PLACE = 1 << 16
_UNSIGNED = {1: np.uint8, 2: np.uint16, 4: np.uint32, 8: np.uint64}


def _same_bytes(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two arrays of one dtype and shape hold the same bytes."""
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    if a.nbytes < _COMPARE_IN_PLACE or a.dtype.hasobject:
        return a.tobytes() == b.tobytes()
    unsigned = _UNSIGNED.get(a.dtype.itemsize)
    if unsigned is None:
        a, b, unsigned = a.reshape(-1).view(np.uint8), b.reshape(-1).view(np.uint8), np.uint8
    return bool(np.array_equal(a.view(unsigned), b.view(unsigned)))
