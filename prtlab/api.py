"""The public entry points: ``shade``, ``precompute`` and ``render_image``, dispatching by method name.

:func:`method_options` lists the options each method takes with their types, so front ends (the
``prtlab`` command's ``-o key=value``) can type and check them before any work.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import typing
from pathlib import Path

from prtlab import _compile_notice
from prtlab._validate import check_int
from prtlab.scene import Scene, ShadeResult

__all__ = ["METHODS", "PIPELINES", "MethodUnavailable", "shade", "precompute", "render_image", "dask_map",
           "pipeline_class", "method_options", "check_bounces", "option_docs", "options_reference"]


class MethodUnavailable(NotImplementedError):
    """The method needs something not installed here (e.g. Mitsuba 3 for ``method="mitsuba"``)."""


# method name -> (module, function) of its shade entry point.
METHODS: dict[str, tuple[str, str]] = {
    "reference": ("prtlab.reference", "shade_reference"),
    "mitsuba": ("prtlab.reference", "shade_mitsuba"),
    "interreflection": ("prtlab.interreflection", "shade_scene"),
    "spherelights": ("prtlab.spherelights", "shade_scene"),
    "portals": ("prtlab.portals", "shade_scene"),
}


# pipeline method name -> (module, class) of its Precomputation subclass.
PIPELINES: dict[str, tuple[str, str]] = {
    "interreflection": ("prtlab.interreflection", "Interreflection"),
    "spherelights": ("prtlab.spherelights", "SphereLights"),
    "portals": ("prtlab.portals", "Portals"),
}

# Parameters of an entry point that are not method options: the front end sets them.
_NOT_OPTIONS = ("scene", "bounces", "progress", "cache", "options", "map_fn")


def pipeline_class(method: str):
    """The :class:`prtlab.pipeline.Precomputation` subclass of a pipeline method, or None for a reference."""
    _entry_point(method)
    if method not in PIPELINES:
        return None
    module, name = PIPELINES[method]
    return getattr(importlib.import_module(module), name)


def method_options(method: str) -> dict[str, typing.Any]:
    """The options ``method`` takes, ``{name: type}``, in declaration order.

    A pipeline's options are the fields of its options dataclass (``options_type``); a
    reference's are the keyword parameters of its shade function (``n_samples``, ``seed``, ...).
    ``scene``, ``bounces`` and ``progress`` are arguments of :func:`shade`, not options.
    """
    cls = pipeline_class(method)
    if cls is not None:
        if cls.options_type is None:
            return {}
        hints = typing.get_type_hints(cls.options_type)
        return {f.name: hints.get(f.name, typing.Any) for f in dataclasses.fields(cls.options_type)}
    function = _entry_point(method)
    hints = typing.get_type_hints(function)
    return {name: hints.get(name, typing.Any) for name, p in inspect.signature(function).parameters.items()
            if name not in _NOT_OPTIONS and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}


def check_bounces(method: str, bounces) -> int:
    """``bounces`` as an int >= 0 that ``method`` can compute, checked before any work."""
    bounces = check_int(bounces, "bounces", 0)
    cls = pipeline_class(method)
    if cls is not None and cls.max_bounces is not None and bounces > cls.max_bounces:
        raise ValueError(
            f"method {method!r} computes at most {cls.max_bounces} indirect bounce(s), "
            f"got bounces={bounces}; use method='reference' for more"
        )
    return bounces


def _entry_point(method: str):
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    module, function = METHODS[method]
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
    bounces = check_bounces(method, bounces)
    _compile_notice.install()
    if isinstance(scene, (str, Path)):
        from prtlab.scene import load_scene

        scene = load_scene(scene)
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a prtlab.Scene or a scene file path, got {type(scene).__name__}")
    return entry_point(scene, bounces=bounces, **options)


def precompute(scene, method: str, workers: int | None = None, scheduler: str | None = None,
               progress: bool = True, timeout: float = 10.0, **options):
    """Run (or load from the cache) the precomputation of a pipeline method.

    Parameters
    ----------
    scene : Scene or path
    method : {"interreflection", "spherelights", "portals"}
    workers, scheduler
        Distribute the precomputation's chunks with Dask: ``workers`` local
        worker processes (a ``LocalCluster``), or the address of a running
        Dask scheduler. Only ``resumable`` methods (their chunks run through
        :meth:`prtlab.pipeline.Precomputation.run_chunks`) can distribute; the
        others raise :class:`MethodUnavailable`.
    progress : bool
        Progress bars.
    timeout : float
        Seconds to wait for ``scheduler`` to answer (then ``ConnectionError``).
    **options
        The method's options.

    Returns
    -------
    The method's :class:`prtlab.pipeline.Precomputation`; call ``.shade(state)`` per frame.
    """
    _entry_point(method)  # unknown / unavailable methods fail here, before any work
    if method not in PIPELINES:
        raise ValueError(f"method {method!r} has no precomputation: it estimates radiance directly")
    options = pipeline_class(method).make_options(options or None)  # bad options fail before any work
    _compile_notice.install()
    if isinstance(scene, (str, Path)):
        from prtlab.scene import load_scene

        scene = load_scene(scene)
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a prtlab.Scene or a scene file path, got {type(scene).__name__}")
    cls = pipeline_class(method)
    map_fn = None
    if workers is not None or scheduler is not None:
        if not cls.resumable:
            raise MethodUnavailable(
                f"method {method!r} cannot distribute its precomputation yet; run it without --workers/--scheduler"
            )
        map_fn = dask_map(workers=workers, scheduler=scheduler, timeout=timeout)
    return cls.precompute(scene, options, progress=progress, map_fn=map_fn)


def dask_map(workers: int | None = None, scheduler: str | None = None, client=None, timeout: float = 10.0):
    """A ``map_fn`` for :meth:`prtlab.cache.Cache.get_or_compute_chunks` that runs chunks on Dask.

    ``client`` (a ``dask.distributed.Client``), else a client of the scheduler at
    ``scheduler``, else a ``LocalCluster`` of ``workers`` single-threaded
    processes. Finished chunks are yielded as they complete, so each is stored
    (and survives an interruption) as soon as it is done.

    A scheduler that cannot be reached within ``timeout`` seconds raises
    ``ConnectionError`` naming its address.
    """
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError as error:
        raise MethodUnavailable(
            "distributed precomputation needs Dask: pip install 'prtlab[distributed]'"
        ) from error
    if client is None:
        if scheduler is not None:
            if not isinstance(timeout, (int, float)) or isinstance(timeout, bool) or not timeout > 0:
                raise ValueError(f"timeout must be a number of seconds > 0, got {timeout!r}")
            try:
                client = Client(scheduler, timeout=timeout)
            except (OSError, TimeoutError, ValueError) as error:
                raise ConnectionError(
                    f"cannot reach the Dask scheduler at {scheduler!r} within {timeout:g} s "
                    f"({type(error).__name__}: {str(error).splitlines()[0] if str(error) else 'no answer'}); "
                    "start it (dask scheduler) or check the address"
                ) from None
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


# ----------------------------------------------------------------------------- the options reference


def option_docs(options_type) -> dict[str, tuple[str, str]]:
    """``{option: (type, description)}`` from the numpydoc ``Attributes`` section of an options dataclass's
    docstring.

    An entry ``a, b : type`` documents both ``a`` and ``b``; the description is the entry's indented text
    joined into one line.
    """
    lines = inspect.cleandoc(options_type.__doc__ or "").splitlines()
    try:
        start = lines.index("Attributes") + 2
    except ValueError:
        return {}
    docs: dict[str, list[str]] = {}
    types: dict[str, str] = {}
    names: list[str] = []
    for line in lines[start:]:
        if line and not line.startswith(" "):
            if " : " not in line:
                break  # the next section
            head, kind = line.split(" : ", 1)
            names = [n.strip() for n in head.split(",")]
            for name in names:
                docs[name], types[name] = [], kind.strip()
        elif line.strip():
            for name in names:
                docs[name].append(line.strip())
    return {name: (types[name], " ".join(text)) for name, text in docs.items()}


def _markdown(text: str) -> str:
    """reST inline markup of a docstring as Markdown in a table cell (roles dropped, ``x`` as `x`, | escaped)."""
    import re

    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"`\1`", text).replace("``", "`")
    return text.replace("|", "\\|")


def options_reference() -> str:
    """The Markdown of ``docs/OPTIONS.md``: every option of every pipeline, with type, default and description.

    Generated from the options dataclasses (``python -m prtlab.api --options-doc > docs/OPTIONS.md``);
    ``tests/test_options_doc.py`` checks that the file is current. An option without a docstring entry
    raises ValueError.
    """
    out = ["# Pipeline options", "",
           "Generated by `python -m prtlab.api --options-doc > docs/OPTIONS.md` from the options dataclasses; "
           "do not edit by hand.", "",
           "Pass options as keywords (`prtlab.shade(scene, method=..., bounces=1, **options)`), as a dict "
           "(`Pipeline.precompute(scene, options)`) or on the command line (`prtlab shade -o name=value`). "
           "`bounces` is an argument of `shade`, not an option (default 1 for every method).", ""]
    for method, (module, name) in PIPELINES.items():
        cls = getattr(importlib.import_module(module), name)
        options_type = cls.options_type
        docs = option_docs(options_type)
        out += [f"## {method}", "", f"`{module}.{options_type.__name__}`", "",
                "| option | type | default | description |", "|---|---|---|---|"]
        for f in dataclasses.fields(options_type):
            if f.name not in docs:
                raise ValueError(f"option {f.name!r} of {options_type.__name__} has no entry in its docstring's "
                                 "Attributes section; document it there")
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            kind, doc = docs[f.name]
            out.append(f"| `{f.name}` | {_markdown(kind)} | `{default!r}` | {_markdown(doc)} |")
        paper = getattr(importlib.import_module(module), "PAPER_OPTIONS", None)
        if paper:
            out += ["", f"The paper's method: `{module}.PAPER_OPTIONS`, "
                    + ", ".join(f"`{k}={v!r}`" for k, v in paper.items())
                    + " (every extension of the package that changes the result off; "
                    + f"`{module}.precompute(scene, {{**options, **PAPER_OPTIONS}})`)."]
        renamed = getattr(cls, "renamed_options", {})
        if renamed:
            out += ["", "Renamed: " + ", ".join(f"`{old}` is now `{new}`" for old, new in sorted(renamed.items()))
                    + "."]
        out.append("")
    return "\n".join(out)


if __name__ == "__main__":
    import sys

    if sys.argv[1:] != ["--options-doc"]:
        sys.exit("usage: python -m prtlab.api --options-doc > docs/OPTIONS.md")
    sys.stdout.write(options_reference())
