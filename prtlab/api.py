"""The public entry points: ``shade`` and ``render_image``, dispatching by method name."""

from __future__ import annotations

import importlib
from pathlib import Path

from prtlab.scene import Scene, ShadeResult

__all__ = ["METHODS", "MethodUnavailable", "shade", "render_image"]


class MethodUnavailable(NotImplementedError):
    """The method exists in the design but is not implemented (or installed) here."""


# method name -> (module, function) of its shade entry point, or the issue that will add it.
METHODS: dict[str, tuple[str, str] | str] = {
    "reference": ("prtlab.reference", "shade_reference"),
    "mitsuba": ("prtlab.reference", "shade_mitsuba"),
    "interreflection": ("prtlab.interreflection", "shade_scene"),
    "spherelights": ("prtlab.spherelights", "shade_scene"),
    "portals": "the Yue et al. portals pipeline (issue 7)",
}


def _entry_point(method: str):
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    target = METHODS[method]
    if isinstance(target, str):
        raise MethodUnavailable(f"method {method!r} is not implemented yet: {target}")
    module, function = target
    return getattr(importlib.import_module(module), function)


def shade(scene, method: str = "reference", bounces: int = 1, **options) -> ShadeResult:
    """Per-vertex outgoing radiance of every object of ``scene`` by ``method``.

    Parameters
    ----------
    scene : Scene or path
        A scene, or the path of a scene file.
    method : {"reference", "mitsuba", "interreflection", "spherelights", "portals"}
    bounces : int
        Indirect bounces (0 = direct light only). A method that cannot do as
        many raises instead of silently doing fewer.
    **options
        Passed to the method (e.g. ``n_samples``, ``seed`` for the references).

    Returns
    -------
    ShadeResult
        ``direct[name]``, ``indirect[name]``, ``total[name]``: (n_vertices, 3).
    """
    if isinstance(scene, (str, Path)):
        from prtlab.scene import load_scene

        scene = load_scene(scene)
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a prtlab.Scene or a scene file path, got {type(scene).__name__}")
    if isinstance(bounces, bool) or not isinstance(bounces, int) or bounces < 0:
        raise ValueError(f"bounces must be a non-negative int, got {bounces!r}")
    return _entry_point(method)(scene, bounces=bounces, **options)


def render_image(scene, result: ShadeResult, part: str = "total", **options):
    """(h, w, 3) linear RGB image of ``scene`` from its camera, shading with ``result``."""
    from prtlab.render import render_image as _render_image

    return _render_image(scene, result, part=part, **options)
