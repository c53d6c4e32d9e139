"""The public entry points: ``shade`` and ``render_image``, dispatching by method name."""

from __future__ import annotations

import importlib
from pathlib import Path

from prtlab._validate import check_int
from prtlab.scene import Scene, ShadeResult

__all__ = ["METHODS", "MethodUnavailable", "shade", "precompute", "render_image", "dask_map"]


class MethodUnavailable(NotImplementedError):
    """The method exists in the design but is not implemented (or installed) here."""


# method name -> (module, function) of its shade entry point, or the issue that will add it.
METHODS: dict[str, tuple[str, str] | str] = {
    "reference": ("prtlab.reference", "shade_reference"),
    "mitsuba": ("prtlab.reference", "shade_mitsuba"),
    "interreflection": ("prtlab.interreflection", "shade_scene"),
    "spherelights": ("prtlab.spherelights", "shade_scene"),
    "portals": ("prtlab.portals", "shade_scene"),
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
    entry_point = _entry_point(method)  # before any work: unknown or unavailable methods fail first
    check_int(bounces, "bounces", 0)
    if isinstance(scene, (str, Path)):
        from prtlab.scene import load_scene

        scene = load_scene(scene)
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a prtlab.Scene or a scene file path, got {type(scene).__name__}")
    return entry_point(scene, bounces=bounces, **options)


def precompute(scene, method: str, workers: int | None = None, scheduler: str | None = None,
               progress: bool = True, **options):
    """Run (or load from the cache) the precomputation of a pipeline method.

    Parameters
    ----------
    scene : Scene or path
    method : {"interreflection", "spherelights", "portals"}
    workers, scheduler
        Distribute the precomputation's chunks with Dask: ``workers`` local
        worker processes (a ``LocalCluster``), or the address of a running
        Dask scheduler. Only methods whose ``precompute`` takes ``map_fn``
        can distribute; the others raise :class:`MethodUnavailable`.
    **options
        The method's options.

    Returns
    -------
    The method's :class:`prtlab.pipeline.Precomputation`; call ``.shade(state)`` per frame.
    """
    import inspect

    _entry_point(method)  # unknown / unavailable methods fail here, before any work
    if method in ("reference", "mitsuba"):
        raise ValueError(f"method {method!r} has no precomputation: it estimates radiance directly")
    if isinstance(scene, (str, Path)):
        from prtlab.scene import load_scene

        scene = load_scene(scene)
    module = importlib.import_module(f"prtlab.{method}")
    kwargs = {"progress": progress}
    if workers is not None or scheduler is not None:
        if "map_fn" not in inspect.signature(module.precompute).parameters:
            raise MethodUnavailable(
                f"method {method!r} cannot distribute its precomputation yet; run it without --workers/--scheduler"
            )
        kwargs["map_fn"] = dask_map(workers=workers, scheduler=scheduler)
    return module.precompute(scene, options or None, **kwargs)


def dask_map(workers: int | None = None, scheduler: str | None = None, client=None):
    """A ``map_fn`` for :meth:`prtlab.cache.Cache.get_or_compute_chunks` that runs chunks on Dask.

    ``client`` (a ``dask.distributed.Client``), else a client of the scheduler at
    ``scheduler``, else a ``LocalCluster`` of ``workers`` single-threaded
    processes. Finished chunks are yielded as they complete, so each is stored
    (and survives an interruption) as soon as it is done.
    """
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError as error:
        raise MethodUnavailable(
            "distributed precomputation needs Dask: pip install 'prtlab[distributed]'"
        ) from error
    if client is None:
        if scheduler is not None:
            client = Client(scheduler)
        else:
            if workers is not None and (isinstance(workers, bool) or int(workers) < 1):
                raise ValueError(f"workers must be a positive int, got {workers!r}")
            client = Client(LocalCluster(n_workers=workers, threads_per_worker=1, processes=True))

    def map_fn(chunk_fn, indices):
        futures = {client.submit(chunk_fn, i, pure=False): i for i in indices}
        for future in as_completed(futures):
            yield futures[future], future.result()

    return map_fn


def render_image(scene, result: ShadeResult, part: str = "total", **options):
    """(h, w, 3) linear RGB image of ``scene`` from its camera, shading with ``result``."""
    from prtlab.render import render_image as _render_image

    return _render_image(scene, result, part=part, **options)
