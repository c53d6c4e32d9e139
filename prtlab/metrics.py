"""Error numbers of one shading against a reference: per object, for direct / indirect / total.

Every whole-scene and Monte Carlo comparison in prtlab goes through :func:`compare`, so a
number in a test, a notebook, a benchmark or ``prtlab compare`` means the same thing.

For an object with per-vertex radiance ``x`` (ours) and ``r`` (reference), both ``(n, 3)``,
and the reference's per-vertex standard error ``s`` (Monte Carlo references only)::

    rel_rms    = sqrt(mean((x - r)^2) / mean(r^2))     # over vertices and channels
    noise      = sqrt(mean(s^2) / mean(r^2))           # the reference's own relative noise
    error      = sqrt(max(rel_rms^2 - noise^2, 0))     # the noise removed, in quadrature
    mean_ratio = mean(x) / mean(r)

The reference's noise is independent of our error, so ``rel_rms^2 = error^2 + noise^2`` in
expectation: noise is combined **in quadrature**, never added. A goal ``g`` on ``error`` is
met when ``rel_rms <= hypot(g, noise)`` (:func:`budget`). A reference is fit to judge a goal
only if its noise is small beside it; :meth:`Comparison.check` refuses a reference whose
noise exceeds a third of the goal.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from typing import Iterable, Mapping

import numpy as np

__all__ = ["PARTS", "ComparisonRow", "Comparison", "compare", "budget"]

PARTS = ("direct", "indirect", "total")


def budget(goal: float, noise: float) -> float:
    """The largest ``rel_rms`` that meets ``goal`` against a reference of relative noise ``noise``:
    ``hypot(goal, noise)`` (independent errors add in quadrature)."""
    return math.hypot(float(goal), float(noise))


@dataclass(frozen=True)
class ComparisonRow:
    """The error numbers of one object's one part (see the module docstring)."""

    object: str
    part: str
    n_vertices: int
    rel_rms: float
    noise: float
    error: float
    mean_ratio: float

    def meets(self, goal: float) -> bool:
        """``rel_rms <= hypot(goal, noise)``."""
        return self.rel_rms <= budget(goal, self.noise)


def _row(name: str, part: str, ours: np.ndarray, ref: np.ndarray, stderr: np.ndarray | None) -> ComparisonRow:
    ours, ref = np.asarray(ours, dtype=np.float64), np.asarray(ref, dtype=np.float64)
    if ours.shape != ref.shape:
        raise ValueError(f"object {name!r} {part}: result has shape {ours.shape}, reference {ref.shape}")
    if not (np.all(np.isfinite(ours)) and np.all(np.isfinite(ref))):
        raise ValueError(f"object {name!r} {part}: non-finite radiance in the result or the reference")
    scale = float(np.mean(ref**2)) if ref.size else 0.0
    if scale == 0.0:  # a black reference: relative numbers are undefined
        nan = float("nan")
        return ComparisonRow(name, part, len(ref), nan, nan, nan, nan)
    rel_rms = math.sqrt(float(np.mean((ours - ref) ** 2)) / scale)
    noise = 0.0 if stderr is None else math.sqrt(float(np.mean(np.asarray(stderr, dtype=np.float64) ** 2)) / scale)
    error = math.sqrt(max(rel_rms**2 - noise**2, 0.0))
    mean_ref = float(np.mean(ref))
    ratio = float(np.mean(ours)) / mean_ref if mean_ref != 0.0 else float("nan")
    return ComparisonRow(name, part, len(ref), rel_rms, noise, error, ratio)


@dataclass(frozen=True)
class Comparison:
    """Rows of :class:`ComparisonRow`, one per (object, part)."""

    rows: tuple[ComparisonRow, ...]

    def row(self, obj: str, part: str) -> ComparisonRow:
        """The row of object ``obj`` and part ``part``."""
        for r in self.rows:
            if r.object == obj and r.part == part:
                return r
        raise KeyError(f"no comparison for object {obj!r}, part {part!r}")

    @property
    def objects(self) -> list[str]:
        return list(dict.fromkeys(r.object for r in self.rows))

    def check(self, goal: float, parts: Iterable[str] = PARTS, objects: Iterable[str] | None = None) -> list[str]:
        """Failures of ``goal`` (a relative-RMS goal on ``error``) as readable lines; empty if all met.

        Raises ``ValueError`` if a reference's noise exceeds ``goal / 3`` (the reference is too
        noisy to judge the goal: sample it more).
        """
        parts, wanted = set(parts), None if objects is None else set(objects)
        failures = []
        for r in self.rows:
            if r.part not in parts or (wanted is not None and r.object not in wanted):
                continue
            if r.noise > goal / 3:
                raise ValueError(
                    f"the reference of {r.object!r} {r.part} has relative noise {r.noise:.3f} > goal/3 = {goal / 3:.3f}: "
                    "sample the reference more"
                )
            if not r.meets(goal):
                failures.append(f"{r.object} {r.part}: rel_rms {r.rel_rms:.4f} > hypot(goal {goal}, noise "
                                f"{r.noise:.4f}) = {budget(goal, r.noise):.4f} (error {r.error:.4f})")
        return failures

    def table(self) -> str:
        """A plain-text table, one line per (object, part)."""
        lines = [f"{'object':<20} {'part':<8} {'vertices':>8} {'rel_rms':>8} {'noise':>7} {'error':>7} {'mean ratio':>10}"]
        for r in self.rows:
            lines.append(f"{r.object:<20} {r.part:<8} {r.n_vertices:>8d} {r.rel_rms:>8.4f} {r.noise:>7.4f} "
                         f"{r.error:>7.4f} {r.mean_ratio:>10.4f}")
        return "\n".join(lines)

    def to_dict(self, json_safe: bool = False) -> dict:
        """``{"rows": [...]}`` of plain numbers (NaN for an all-black reference; ``None`` instead
        if ``json_safe``, since JSON has no NaN)."""
        rows = [asdict(r) for r in self.rows]
        if json_safe:
            rows = [{k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in row.items()}
                    for row in rows]
        return {"rows": rows}

    def to_json(self, path) -> None:
        """Write :meth:`to_dict` as JSON (NaN written as ``null``)."""
        with open(path, "w", encoding="utf-8") as f:
            json.dump(self.to_dict(json_safe=True), f, indent=2)


def compare(result, reference, objects: Iterable[str] | None = None, parts: Iterable[str] = PARTS,
            masks: Mapping[str, np.ndarray] | None = None) -> Comparison:
    """Error numbers of ``result`` against ``reference`` (two :class:`prtlab.ShadeResult`).

    Parameters
    ----------
    result, reference : ShadeResult
        ``reference.stderr[part][name]`` (Monte Carlo references) is the reference's noise;
        without it the noise is 0.
    objects : names, optional
        The objects to score; default every object of ``reference`` (each must be in ``result``).
    parts : names
        Any of ``"direct"``, ``"indirect"``, ``"total"``.
    masks : {name: (n_vertices,) bool}, optional
        Score only these vertices of an object (e.g. leave out vertices the camera never sees).

    Returns
    -------
    Comparison
        One :class:`ComparisonRow` per (object, part), in the order given.
    """
    parts = tuple(parts)
    bad = [p for p in parts if p not in PARTS]
    if bad:
        raise ValueError(f"parts must be among {PARTS}, got {bad}")
    names = list(reference.total) if objects is None else list(objects)
    rows = []
    for name in names:
        for part in parts:
            ref_part, our_part = getattr(reference, part), getattr(result, part)
            if name not in ref_part:
                raise KeyError(f"the reference has no {part} radiance for object {name!r}")
            if name not in our_part:
                raise KeyError(f"the result has no {part} radiance for object {name!r}")
            stderr = reference.stderr.get(part, {}).get(name)
            ours, ref = our_part[name], ref_part[name]
            if masks is not None and name in masks:
                keep = np.asarray(masks[name], dtype=bool)
                ours, ref = np.asarray(ours)[keep], np.asarray(ref)[keep]
                stderr = None if stderr is None else np.asarray(stderr)[keep]
            rows.append(_row(name, part, ours, ref, stderr))
    return Comparison(tuple(rows))
