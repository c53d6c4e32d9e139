"""Per-vertex outgoing radiance of a shaded scene: what every method returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["ShadeResult"]

_PARTS = ("direct", "indirect", "total")


@dataclass
class ShadeResult:
    """Outgoing radiance toward the camera at every vertex of every object.

    ``direct[name]``, ``indirect[name]`` and ``total[name]`` are
    ``(n_vertices, 3)`` float64 arrays (``total = direct + indirect``).
    Monte Carlo methods also fill ``stderr`` with the standard error of each
    part, same keys and shapes. ``info`` holds scalars such as timings,
    sample counts and the method name.
    """

    direct: dict[str, np.ndarray] = field(default_factory=dict)
    indirect: dict[str, np.ndarray] = field(default_factory=dict)
    total: dict[str, np.ndarray] = field(default_factory=dict)
    stderr: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    @classmethod
    def from_vertex_arrays(cls, names, counts, parts: dict, stderr: dict | None = None) -> "ShadeResult":
        """Split ``parts[part]`` (and ``stderr[part]``), ``(sum(counts), 3)`` arrays over the objects ``names``
        in order, ``counts[i]`` rows each (copies)."""
        result = cls()
        bounds = np.concatenate([[0], np.cumsum(counts)]).astype(int)
        for part, values in parts.items():
            getattr(result, part).update({n: values[a:b].copy() for n, a, b in zip(names, bounds[:-1], bounds[1:])})
        for part, values in (stderr or {}).items():
            result.stderr[part] = {n: values[a:b].copy() for n, a, b in zip(names, bounds[:-1], bounds[1:])}
        return result

    def save_npz(self, path) -> Path:
        """Write ``<object>/direct|indirect|total`` (and ``<object>/stderr_<part>``) arrays."""
        arrays = {}
        for part in _PARTS:
            for name, values in getattr(self, part).items():
                arrays[f"{name}/{part}"] = np.asarray(values)
        for part, per_object in self.stderr.items():
            for name, values in per_object.items():
                arrays[f"{name}/stderr_{part}"] = np.asarray(values)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, **arrays)
        return path

    @classmethod
    def load_npz(cls, path) -> "ShadeResult":
        """Read a file written by :meth:`save_npz` (no pickle: plain arrays only)."""
        result = cls()
        with np.load(path, allow_pickle=False) as data:
            for key in data.files:
                name, part = key.rsplit("/", 1)
                if part in _PARTS:
                    getattr(result, part)[name] = data[key]
                elif part.startswith("stderr_"):
                    result.stderr.setdefault(part[len("stderr_"):], {})[name] = data[key]
        return result
