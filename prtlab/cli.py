"""The ``prtlab`` command: a thin layer over :mod:`prtlab.api`.

::

    prtlab --version
    prtlab shade SCENE --method M [--bounces B] [--samples N] [--seed S] [-o KEY=VALUE ...] [--out radiance.npz]
    prtlab render SCENE --method M [--frames N] [--exposure STOPS] [-o KEY=VALUE ...] --out DIR
    prtlab compare SCENE --methods M1,M2 [--reference reference|mitsuba] [--bounces B] [--samples N]
                   [-o [METHOD.]KEY=VALUE ...] [--out DIR]
    prtlab precompute SCENE --method M [-o KEY=VALUE ...] [--workers N | --scheduler ADDRESS]
    prtlab cache info|list|clear [--method M]
    prtlab reproduce [--quick] [--out report/] [--only NAME] [--write-docs [PATH]]
    prtlab bench [--quick] [--json bench.json] [--select NAME] [--threads N] [--write-docs [PATH]]

Methods: ``reference`` and ``mitsuba`` (Monte Carlo ground truth) and the pipelines
``interreflection``, ``spherelights`` and ``portals``.

Method options
--------------
``-o KEY=VALUE`` (repeatable) sets one option of the method, typed by the method's options
(a pipeline's options dataclass, e.g. :class:`prtlab.spherelights.SphereLightOptions`; a
reference's keyword arguments, e.g. ``n_samples``). Values are ints, numbers, ``true``/``false``,
strings, or YAML/JSON flow text for mappings and lists::

    prtlab shade scene.yaml --method spherelights -o n_spheres=4 -o 'n_spheres={bunny: 8, floor: 1}'
    prtlab shade scene.yaml --method interreflection -o n_lights=64 -o shadows=haar

``--seed`` and ``--samples`` set a method's ``seed`` and ``n_samples`` options; they are passed
only when given and refused for a method that has no such option. A pipeline that stores a number
of bounces (portals' ``bounces`` option) stores ``--bounces`` of them unless ``-o bounces=K`` asks
for more (to reuse one precomputation for several ``--bounces``). With ``compare``, an option
``METHOD.KEY=VALUE`` goes to that method only, a bare ``KEY=VALUE`` to every method of the run
that has ``KEY``.

Outputs
-------
``shade --out`` writes one ``.npz`` (keys ``<object>/direct|indirect|total``): a folder gets
``radiance.npz`` inside it, a name without ``.npz`` gets it appended, and the path written is
printed. ``render --out`` gets ``frame_NNNN.png`` and ``.exr`` per frame; a pipeline is
precomputed once and each frame shades its :class:`prtlab.pipeline.FrameState`. ``compare --out``
gets ``compare.json`` (every row of :func:`prtlab.compare` per method) and per method a
difference image, a side-by-side comparison and a per-vertex agreement plot. Every output is
checked to be writable before any work.

Errors and logs
---------------
A user error is one line on stderr: exit code 2 for a bad command line (or a method not
installed here), 1 for an error while running. ``PRTLAB_DEBUG=1`` shows the traceback instead.
Log records of the ``prtlab.*`` loggers at INFO and above (e.g. cache hits and misses) are
printed as one line each on stderr; ``-q`` shows only warnings and errors, with no progress bars.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import sys
import tempfile
import time
import types
import typing
import warnings
from pathlib import Path

METHOD_NAMES = ("reference", "mitsuba", "interreflection", "spherelights", "portals")
REFERENCE_NAMES = ("reference", "mitsuba")

_MITSUBA_MISSING = "method 'mitsuba' needs Mitsuba 3: pip install 'prtlab[reference]'"


class UsageError(ValueError):
    """A bad command line found after parsing (an option a method does not take, a bad value)."""


class _Parser(argparse.ArgumentParser):
    """argparse, with each error as one line (no usage block)."""

    def error(self, message):
        message = " ".join(str(message).split())
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


# --------------------------------------------------------------------------- argument types


def _int_at_least(minimum: int, meaning: str = ""):
    def parse(text: str) -> int:
        what = f"must be an int >= {minimum}" + (f" ({meaning})" if meaning else "")
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what}, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"{what}, got {value}")
        return value

    parse.__name__ = "int"
    return parse


def _float_in(what: str, accept):
    """An argparse type: a float for which ``accept(value)`` holds, else ``must be <what>, got <text>``."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = None
        if value is None or not accept(value):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        return value

    parse.__name__ = "float"
    return parse


_positive_float = _float_in("a number of seconds > 0", lambda v: 0 < v < float("inf"))
_finite_float = _float_in("a finite number", math.isfinite)


def _option_pair(text: str) -> tuple[str | None, str, str]:
    """``[METHOD.]KEY=VALUE`` -> ``(method or None, key, value text)``."""
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"must be KEY=VALUE (e.g. -o n_spheres=4), got {text!r}")
    scope, dot, name = key.rpartition(".")
    if dot and (not scope or not name):
        raise argparse.ArgumentTypeError(f"must be KEY=VALUE or METHOD.KEY=VALUE, got {text!r}")
    return (scope or None, name, value)


def _method_list(text: str) -> list[str]:
    names = [name.strip() for name in text.split(",")]
    if any(not name for name in names):
        raise argparse.ArgumentTypeError(f"must be method names separated by commas, got {text!r}")
    unknown = [name for name in names if name not in METHOD_NAMES]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown method(s) {', '.join(map(repr, unknown))}; "
                                         f"choose from {', '.join(METHOD_NAMES)}")
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise argparse.ArgumentTypeError(f"method(s) {', '.join(map(repr, repeated))} listed more than once")
    return names


# --------------------------------------------------------------------------- the parser


def _parser() -> argparse.ArgumentParser:
    from prtlab import __version__

    parser = _Parser(prog="prtlab", description="Precomputed radiance transfer for dynamic scenes: shade, "
                     "render and compare scenes with the papers' methods and Monte Carlo references.")
    parser.add_argument("--version", action="version", version=f"prtlab {__version__}",
                        help="print the version and exit")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="print only results, warnings and errors (no progress bars or log lines)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser,
                                help="what to do (prtlab COMMAND --help for its flags)")
    _add_shading_commands(sub)
    _add_tool_commands(sub)
    return parser


def _add_command(sub, name, **kwargs):
    p = sub.add_parser(name, **kwargs)
    p.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                   help="as prtlab -q: no progress bars or log lines")
    return p


def _scene_arg(p):
    p.add_argument("scene", help="scene file (YAML, see docs/SCENE_FORMAT.md) or the name of a shipped scene, "
                                "e.g. cornell_box")


def _shading_args(p, method: bool = True):
    if method:
        p.add_argument("--method", required=True, choices=METHOD_NAMES,
                       help="shading method: a Monte Carlo reference or a pipeline")
    p.add_argument("--bounces", type=_int_at_least(0, "0 = direct light only"), default=1, metavar="B",
                   help="indirect bounces (0 = direct light only; default 1)")
    p.add_argument("--samples", type=_int_at_least(1), default=None, metavar="N",
                   help="Monte Carlo samples per vertex (the n_samples option of a reference)")
    p.add_argument("--seed", type=_int_at_least(0), default=None, metavar="S",
                   help="random seed (the seed option of the methods that draw random numbers)")
    scoped = "" if method else ("; METHOD.KEY=VALUE sets it for one method only, KEY=VALUE for every "
                                "method of the run that has KEY")
    p.add_argument("-o", "--option", dest="options", action="append", type=_option_pair, default=[],
                   metavar="KEY=VALUE",
                   help="a method option, repeatable, e.g. -o n_spheres=4 or -o 'n_spheres={bunny: 8}'; "
                        "a wrong key lists the valid ones" + scoped)


def _add_shading_commands(sub):
    """``shade``, ``render`` and ``compare``: the commands that shade a scene."""
    p = _add_command(sub, "shade", help="per-vertex radiance of a scene, saved as .npz",
                     description="Per-vertex radiance of every object of a scene by one method.")
    _scene_arg(p)
    _shading_args(p)
    p.add_argument("--out", default="radiance.npz",
                   help="output .npz (keys <object>/direct|indirect|total); a folder gets radiance.npz inside, "
                        "a name without .npz gets .npz appended (default radiance.npz)")

    p = _add_command(sub, "render", help="images of a scene, one per animation frame",
                     description="Render the scene's camera view for each animation frame. A pipeline is "
                                 "precomputed once; each frame then shades its own frame state.")
    _scene_arg(p)
    _shading_args(p)
    p.add_argument("--frames", type=_int_at_least(1), default=1, metavar="N",
                   help="frames spread evenly over the scene's animation (>= 1; default 1)")
    p.add_argument("--out", required=True, help="output folder (frame_NNNN.png and .exr per frame)")
    p.add_argument("--exposure", type=_finite_float, default=0.0, help="exposure of the PNGs in stops (default 0)")

    p = _add_command(sub, "compare", help="error numbers of methods against a reference",
                     description="Shade a scene with each method and a reference; print per object the "
                                 "relative RMS error of direct, indirect and total light (prtlab.compare).")
    _scene_arg(p)
    p.add_argument("--methods", required=True, type=_method_list,
                   help=f"methods to score, separated by commas (from {', '.join(METHOD_NAMES)})")
    p.add_argument("--reference", choices=REFERENCE_NAMES, default="reference",
                   help="the ground truth (default: prtlab's own Monte Carlo reference)")
    _shading_args(p, method=False)
    p.add_argument("--out", default=None,
                   help="output folder: compare.json (every row) and per method difference, comparison and "
                        "agreement images")


def _add_tool_commands(sub):
    """``precompute``, ``cache``, ``reproduce`` and ``bench``."""
    p = _add_command(sub, "precompute", help="run and cache a pipeline's precomputation",
                     description="Run a pipeline's precomputation (or find it in the cache), optionally "
                                 "on Dask workers.")
    _scene_arg(p)
    p.add_argument("--method", required=True, choices=METHOD_NAMES, help="the pipeline to precompute")
    p.add_argument("-o", "--option", dest="options", action="append", type=_option_pair, default=[],
                   metavar="KEY=VALUE", help="a method option, repeatable (as for shade)")
    group = p.add_mutually_exclusive_group()
    group.add_argument("--workers", type=_int_at_least(1), default=None, help="local Dask worker processes")
    group.add_argument("--scheduler", default=None, help="address of a running Dask scheduler (tcp://host:port)")
    p.add_argument("--timeout", type=_positive_float, default=10.0,
                   help="seconds to wait for --scheduler to answer (default 10)")

    p = _add_command(sub, "cache", help="show or clear the cache of precomputations",
                     description="The cache of precomputations ($PRTLAB_CACHE, default ~/.cache/prtlab).")
    p.add_argument("action", choices=("info", "list", "clear"),
                   help="info: size and entries per method; list: one line per entry; clear: delete entries")
    p.add_argument("--method", default=None, help="only the entries of this method (e.g. portals)")

    from prtlab.bench import add_arguments as add_bench_arguments
    from prtlab.reproduce import add_arguments as add_reproduce_arguments

    add_reproduce_arguments(_add_command(
        sub, "reproduce", help="every paper figure and table that exists so far, as report/index.html",
        description="Run every notebook headless and gather their figures and tables."))
    add_bench_arguments(_add_command(
        sub, "bench", help="benchmarks, with peers and the machine's peak measured in the same run",
        description="Time the benchmark cases (medians after a warm-up)."))


# --------------------------------------------------------------------------- method options


def _type_name(tp) -> str:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        names = [_type_name(a) for a in typing.get_args(tp) if a is not type(None)]
        none = " or none" if type(None) in typing.get_args(tp) else ""
        return " or ".join(names) + none
    base = origin or tp
    return {int: "an int", float: "a number", bool: "true or false", str: "a string",
            dict: "a mapping such as {key: value}", list: "a list such as [a, b]",
            tuple: "a list such as [a, b]"}.get(base, "a YAML value")


def _parse_value(text: str, tp):
    """``text`` as a value of type ``tp``; ValueError if it is not one."""
    import yaml

    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if type(None) in args and text.strip().lower() in ("none", "null"):
            return None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _parse_value(text, arg)
            except ValueError:
                continue
        raise ValueError(text)
    base = origin or tp
    s = text.strip()
    if base is bool:
        lowered = s.lower()
        if lowered in ("true", "1", "yes", "on"):
            return True
        if lowered in ("false", "0", "no", "off"):
            return False
        raise ValueError(text)
    if base is int:
        return int(s)  # "2.7" and "1e3" are not ints (floats are not ints)
    if base is float:
        return float(s)
    if base is str:
        return text
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        raise ValueError(text) from None
    if base is dict and not isinstance(value, dict):
        raise ValueError(text)
    if base in (list, tuple):
        if not isinstance(value, list):
            raise ValueError(text)
        return tuple(value) if base is tuple else value
    return value


def _takes(method: str) -> dict:
    from prtlab import api

    return api.method_options(method)


def _typed_options(method: str, pairs, flags: dict) -> dict:
    """The options of ``method``: ``-o`` pairs typed by the method's options, and the flags given.

    ``pairs``: ``(scope, key, text)`` already selected for this method. ``flags``:
    ``{"--seed": ("seed", 3)}`` of the flags the user gave.
    """
    takes = _takes(method)
    options = {}
    for _, key, text in pairs:
        if key not in takes:
            raise UsageError(f"-o {key}={text}: method {method!r} has no option {key!r}; "
                             f"valid: {', '.join(takes) or 'none'}")
        try:
            options[key] = _parse_value(text, takes[key])
        except ValueError:
            raise UsageError(f"-o {key}={text}: option {key!r} of method {method!r} must be "
                             f"{_type_name(takes[key])}, got {text!r}") from None
    for flag, (key, value) in flags.items():
        if key not in takes:
            raise UsageError(f"{flag}: method {method!r} has no {key} option "
                             f"(its options: {', '.join(takes) or 'none'})")
        if key in options:
            raise UsageError(f"{flag} and -o {key}=... both set {key!r} of method {method!r}; give one")
        options[key] = value
    return options


def _flags(args) -> dict:
    flags = {}
    if args.seed is not None:
        flags["--seed"] = ("seed", args.seed)
    if args.samples is not None:
        flags["--samples"] = ("n_samples", args.samples)
    return flags


def _check_method(method: str, bounces: int | None, options: dict) -> None:
    """Refuse, before any work, a method not installed here, too many bounces or bad option values."""
    import importlib.util

    from prtlab import api

    if method == "mitsuba" and importlib.util.find_spec("mitsuba") is None:
        raise api.MethodUnavailable(_MITSUBA_MISSING)
    if bounces is not None:
        api.check_bounces(method, bounces)
    cls = api.pipeline_class(method)
    if cls is not None:
        cls.make_options(options)
        _check_cache_folder()


def _check_cache_folder() -> None:
    """The cache folder of precomputations must be writable before a pipeline starts."""
    from prtlab.cache import default_cache_root

    root = default_cache_root()
    try:
        _writable_folder(root, "cache folder")
    except OSError as error:
        raise OSError(f"{error}; set PRTLAB_CACHE to a writable folder") from None


# --------------------------------------------------------------------------- outputs


def _writable_folder(folder: Path, flag: str) -> Path:
    """Create ``folder`` (with parents) and prove a file can be written there, before any work."""
    if folder.exists() and not folder.is_dir():
        raise OSError(f"{flag} {folder}: is a file, not a folder; give a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".prtlab-write-check-"):
            pass
    except OSError as error:
        raise OSError(f"{flag} {folder}: cannot write there ({error.strerror or error}); "
                      "give a writable folder") from None
    return folder


def _npz_path(out: str) -> Path:
    """The file ``shade --out`` writes: ``radiance.npz`` in a folder, ``.npz`` appended if missing."""
    path = Path(out)
    if path.is_dir() or out.endswith(("/", os.sep)):
        path = path / "radiance.npz"
    elif path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    if path.is_dir():
        raise OSError(f"--out {out}: {path} is a folder; give a file name ending in .npz")
    _writable_folder(path.parent, "--out")
    if path.exists() and not os.access(path, os.W_OK):
        raise OSError(f"--out {out}: {path} exists and is not writable")
    return path


# --------------------------------------------------------------------------- commands


def _stored_bounces(method: str, options: dict, bounces: int) -> dict:
    """A pipeline whose options say how many bounces to store (portals) stores ``--bounces`` unless
    ``-o bounces=K`` asks for more; fewer than ``--bounces`` is refused before any work."""
    if _is_pipeline(method) and "bounces" in _takes(method):
        stored = options.setdefault("bounces", bounces)
        if isinstance(stored, int) and stored < bounces:
            raise UsageError(f"-o bounces={stored} stores fewer bounces than --bounces {bounces}; "
                             f"give -o bounces >= {bounces} (or leave it out)")
    return options


def _is_pipeline(method: str) -> bool:
    from prtlab import api

    return api.pipeline_class(method) is not None


def _shade(scene, method: str, bounces: int, options: dict, progress: bool):
    """``prtlab.shade`` of a reference; a pipeline's precomputation (with its options as given) then one frame."""
    from prtlab import api

    if not _is_pipeline(method):
        return api.shade(scene, method=method, bounces=bounces, progress=progress, **options)
    return api.precompute(scene, method, progress=progress, **options).shade(bounces=bounces)


def _shade_options(args, method: str) -> dict:
    pairs = []
    for scope, key, text in args.options:
        if scope is not None and scope != method:
            raise UsageError(f"-o {scope}.{key}={text}: names method {scope!r}, but --method is {method!r}")
        pairs.append((scope, key, text))
    options = _stored_bounces(method, _typed_options(method, pairs, _flags(args)), args.bounces)
    _check_method(method, args.bounces, options)
    return options


def _cmd_shade(args) -> int:
    from prtlab import api
    from prtlab.scene import load_scene

    options = _shade_options(args, args.method)
    path = _npz_path(args.out)
    scene = load_scene(args.scene)
    start = time.perf_counter()
    result = _shade(scene, args.method, args.bounces, options, progress=not args.quiet)
    seconds = time.perf_counter() - start
    result.save_npz(path)
    print(f"wrote {path} ({len(result.total)} objects, {args.method}, {seconds:.2f} s)")
    return 0


def _cmd_render(args) -> int:
    from prtlab import api
    from prtlab.pipeline import FrameState
    from prtlab.render import save_exr, save_png
    from prtlab.scene import load_scene

    options = _shade_options(args, args.method)
    out = _writable_folder(Path(args.out), "--out")
    scene = load_scene(args.scene)
    n = args.frames
    pre = None
    if args.method not in REFERENCE_NAMES:
        start = time.perf_counter()
        pre = api.precompute(scene, args.method, progress=not args.quiet, **options)
        print(f"{args.method}: precomputed (or loaded from the cache) in {time.perf_counter() - start:.2f} s")
    for frame in range(n):
        frame_scene = scene.at_frame(frame, n) if n > 1 else scene
        start = time.perf_counter()
        if pre is None:
            result = api.shade(frame_scene, method=args.method, bounces=args.bounces, progress=not args.quiet,
                               **options)
        else:
            state = FrameState.from_scene(frame_scene)
            moved = pre.moved_objects(state)
            if moved:  # the method bakes these poses (portals): precompute again where they now stand
                print(f"frame {frame + 1}/{n}: {args.method} bakes the pose of {', '.join(map(repr, moved))}, "
                      "which moved: precomputing again at the new pose", flush=True)
                pre = api.precompute(frame_scene, args.method, progress=not args.quiet, **options)
            result = pre.shade(state, bounces=args.bounces)
        shaded = time.perf_counter()
        image = api.render_image(frame_scene, result)
        imaged = time.perf_counter()
        stem = out / f"frame_{frame:04d}"
        save_png(stem.with_suffix(".png"), image, exposure=args.exposure)
        save_exr(stem.with_suffix(".exr"), image)
        print(f"frame {frame + 1}/{n}: shaded in {shaded - start:.3f} s, image {imaged - shaded:.3f} s "
              f"-> {stem}.png, .exr", flush=True)
    return 0


def _compare_options(args, methods: list[str]) -> dict[str, dict]:
    """Each method's options: ``METHOD.KEY=VALUE`` for that method, ``KEY=VALUE`` for every method having KEY."""
    per_method = {m: [] for m in methods}
    for scope, key, text in args.options:
        if scope is not None:
            if scope not in per_method:
                raise UsageError(f"-o {scope}.{key}={text}: {scope!r} is not among the methods of this run "
                                 f"({', '.join(methods)})")
            per_method[scope].append((scope, key, text))
            continue
        takers = [m for m in methods if key in _takes(m)]
        if not takers:
            raise UsageError(f"-o {key}={text}: no method of this run ({', '.join(methods)}) has option {key!r}; "
                             "use METHOD.KEY=VALUE to aim at one method")
        for m in takers:
            per_method[m].append((None, key, text))
    flags = _flags(args)
    options = {}
    for m in methods:
        given = {flag: kv for flag, kv in flags.items() if kv[0] in _takes(m)}
        options[m] = _stored_bounces(m, _typed_options(m, per_method[m], given), args.bounces)
    for flag, (key, _) in flags.items():
        if not any(key in _takes(m) for m in methods):
            raise UsageError(f"{flag}: no method of this run ({', '.join(methods)}) has a {key} option")
    return options


def _cmd_compare(args) -> int:
    import json

    from prtlab import api
    from prtlab.metrics import compare
    from prtlab.scene import load_scene

    methods = [m for m in args.methods if m != args.reference]
    if not methods:
        raise UsageError(f"--methods lists only the reference {args.reference!r}; name a method to score")
    options = _compare_options(args, [args.reference, *methods])
    for method in (args.reference, *methods):  # bad option values fail the run before any work
        cls = api.pipeline_class(method)
        if cls is not None:
            cls.make_options(options[method])
    _check_method(args.reference, args.bounces, options[args.reference])
    report = {"scene": str(args.scene), "reference": args.reference, "bounces": args.bounces,
              "methods": {}, "failed": {}}
    runnable = []
    for method in methods:  # a method that cannot do these bounces (or is not installed) is left out
        try:
            _check_method(method, args.bounces, options[method])
            runnable.append(method)
        except (ValueError, NotImplementedError) as error:
            report["failed"][method] = _one_line(error)
            print(f"prtlab compare: {method} cannot shade this scene: {report['failed'][method]}", file=sys.stderr)
    if not runnable:
        print(f"prtlab compare: no method can shade this scene with --bounces {args.bounces}", file=sys.stderr)
        return 1
    out = None if args.out is None else _writable_folder(Path(args.out), "--out")
    scene = load_scene(args.scene)

    start = time.perf_counter()
    reference = _shade(scene, args.reference, args.bounces, options[args.reference], progress=not args.quiet)
    print(f"{args.reference}: {time.perf_counter() - start:.2f} s")
    images = {}
    if out is not None:
        images[args.reference] = api.render_image(scene, reference)
    for method in runnable:
        try:
            start = time.perf_counter()
            result = _shade(scene, method, args.bounces, options[method], progress=not args.quiet)
            seconds = time.perf_counter() - start
            comparison = compare(result, reference)
        except (ValueError, TypeError, KeyError, ImportError, NotImplementedError, MemoryError) as error:
            if os.environ.get("PRTLAB_DEBUG"):
                raise
            message = _one_line(error)
            print(f"prtlab compare: {method} cannot shade this scene: {message}", file=sys.stderr)
            report["failed"][method] = message
            continue
        print(f"\n{method} against {args.reference} (bounces {args.bounces}, {seconds:.2f} s):")
        print(comparison.table())
        report["methods"][method] = {"seconds": seconds, "options": _jsonable(options[method]),
                                     **comparison.to_dict(json_safe=True)}
        if out is not None:
            _compare_figures(out, scene, method, args.reference, result, reference, images)
    if out is not None:
        path = out / "compare.json"
        with open(path, "w", encoding="utf-8") as f:
            json.dump(report, f, indent=2)
        print(f"\nwrote {path} and the images in {out}")
    if report["failed"]:
        print(f"prtlab compare: {len(report['failed'])} method(s) failed: {', '.join(report['failed'])}",
              file=sys.stderr)
        return 1
    return 0


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


def _compare_figures(out: Path, scene, method: str, reference_name: str, result, reference, images) -> None:
    """difference_<method>.png, comparison_<method>.png and agreement_<method>.png in ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from prtlab import api
    from prtlab.render import agreement_plot, comparison_figure, difference_figure

    image = api.render_image(scene, result)
    ref_image = images[reference_name]
    figures = {
        "difference": difference_figure(image, ref_image, title=f"{method} vs {reference_name}: relative difference"),
        "comparison": comparison_figure([ref_image, image], [reference_name, method]),
    }
    names = list(reference.total)
    ref_values = np.concatenate([reference.total[n] for n in names])
    values = np.concatenate([result.total[n] for n in names])
    stderr = reference.stderr.get("total", {})
    ref_err = np.concatenate([stderr[n] for n in names]) if all(n in stderr for n in names) else None
    figures["agreement"] = agreement_plot(ref_values, values, ref_err, xlabel=reference_name, ylabel=method,
                                          title=f"total radiance per vertex: {method}")
    for kind, fig in figures.items():
        fig.savefig(out / f"{kind}_{method}.png", dpi=100)
        plt.close(fig)


def _cmd_precompute(args) -> int:
    from prtlab import api

    if args.method in REFERENCE_NAMES:
        print(f"method {args.method!r} has no precomputation: it estimates radiance directly")
        return 0
    pairs = [(s, k, t) for s, k, t in args.options]
    for scope, key, text in pairs:
        if scope is not None and scope != args.method:
            raise UsageError(f"-o {scope}.{key}={text}: names method {scope!r}, but --method is {args.method!r}")
    options = _typed_options(args.method, pairs, {})
    _check_method(args.method, None, options)
    start = time.perf_counter()
    pre = api.precompute(args.scene, args.method, workers=args.workers, scheduler=args.scheduler,
                         timeout=args.timeout, progress=not args.quiet, **options)
    print(f"{args.method}: precomputation of {args.scene} is cached ({type(pre).__name__}, "
          f"{time.perf_counter() - start:.2f} s)")
    return 0


def _size(n_bytes) -> str:
    """``n_bytes`` as a short human-readable size (binary units)."""
    if n_bytes is None:
        return "no cap"
    value = float(n_bytes)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if value < 1024 or unit == "GiB":
            return f"{int(value)} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    return f"{value:.1f} TiB"  # pragma: no cover


def _cmd_cache(args) -> int:
    from prtlab.cache import Cache

    cache = Cache(progress=False)
    if args.action == "clear":
        n_files, n_bytes = cache.clear(method=args.method)
        what = f"entries of method {args.method!r}" if args.method else "entries"
        print(f"removed {n_files} files ({_size(n_bytes)}) of {what} from {cache.root}")
        return 0
    entries = cache.entries(method=args.method)
    if args.action == "list":
        if not entries:
            print(f"no cache entries{f' of method {args.method!r}' if args.method else ''} in {cache.root}")
        for e in sorted(entries, key=lambda e: e.last_used, reverse=True):
            used = time.strftime("%Y-%m-%d %H:%M", time.localtime(e.last_used))
            print(f"{e.method:<16} {e.kind:<6} {_size(e.size_bytes):>10}  used {used}  {e.path}")
        return 0
    info = cache.info()
    print(f"cache folder: {info['root']}")
    per_method: dict[str, list[int]] = {}
    for e in entries:
        count = per_method.setdefault(e.method, [0, 0, 0])  # entries, unfinished parts folders, bytes
        count[0 if e.kind == "entry" else 1] += 1
        count[2] += e.size_bytes
    if args.method:
        n, parts, size = [sum(c[i] for c in per_method.values()) for i in range(3)]
        print(f"method {args.method}: {n} entries, {_size(size)}" + (f", {parts} unfinished" if parts else ""))
    else:
        print(f"{info['n_entries']} entries, {_size(info['total_bytes'])} of {_size(info['max_bytes'])} "
              "(least recently used entries are evicted beyond the cap)")
    for method, (n, parts, size) in sorted(per_method.items()):
        unfinished = f"  ({parts} unfinished)" if parts else ""
        print(f"  {method:<16} {n:>4} entries  {_size(size):>10}{unfinished}")
    return 0


def _cmd_reproduce(args) -> int:
    from prtlab.reproduce import run

    _writable_folder(args.out, "--out")
    return run(args)


def _cmd_bench(args) -> int:
    from prtlab.bench import run_from_args

    if args.json is not None:
        if args.json.is_dir():
            raise OSError(f"--json {args.json}: is a folder; give a file name")
        _writable_folder(args.json.parent, "--json")
    return run_from_args(args)


# --------------------------------------------------------------------------- main


def _one_line(error: BaseException) -> str:
    """The error's message on one line (a bare ``KeyError('x')`` keeps its type: ``KeyError: 'x'``)."""
    if isinstance(error, KeyError) and error.args and " " in str(error.args[0]):
        text = str(error.args[0])  # a sentence, e.g. "no object 'x' in the scene"
    else:
        text = str(error)
        if isinstance(error, KeyError) or not text:
            text = f"{type(error).__name__}: {text}" if text else type(error).__name__
    return " ".join(text.split())


class _OneLineHandler(logging.StreamHandler):
    """Each record as one line, written above any progress bar."""

    def emit(self, record):
        from tqdm import tqdm

        try:
            tqdm.write(" ".join(self.format(record).split()), file=self.stream)
        except Exception:  # noqa: BLE001 - logging must never raise
            self.handleError(record)


@contextlib.contextmanager
def _console(quiet: bool):
    """Log records of ``prtlab.*`` and warnings as one line each on stderr, for the command's duration."""
    from prtlab import _compile_notice

    logger = logging.getLogger("prtlab")
    handler = _OneLineHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
    handler.setLevel(logging.WARNING if quiet else logging.INFO)
    old_level = logger.level
    logger.addHandler(handler)
    if logger.level == logging.NOTSET or logger.level > logging.INFO:
        logger.setLevel(logging.INFO)

    def show(message, category, filename, lineno, file=None, line=None):
        from tqdm import tqdm

        tqdm.write(f"prtlab: {category.__name__}: {' '.join(str(message).split())}", file=sys.stderr)

    with warnings.catch_warnings(), (_compile_notice.suppressed() if quiet else contextlib.nullcontext()):
        warnings.showwarning = show
        try:
            yield
        finally:
            logger.removeHandler(handler)
            logger.setLevel(old_level)


_HANDLERS = {
    "shade": _cmd_shade,
    "render": _cmd_render,
    "compare": _cmd_compare,
    "precompute": _cmd_precompute,
    "cache": _cmd_cache,
    "reproduce": _cmd_reproduce,
    "bench": _cmd_bench,
}


def main(argv=None) -> int:
    """Run the ``prtlab`` command with ``argv`` (default ``sys.argv[1:]``); return the exit code."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exit_:  # --help, --version and argparse errors
        return exit_.code if isinstance(exit_.code, int) else 1
    from prtlab.api import MethodUnavailable

    debug = bool(os.environ.get("PRTLAB_DEBUG"))
    prefix = f"prtlab {args.command}"
    with _console(args.quiet):
        try:
            return _HANDLERS[args.command](args)
        except (UsageError, MethodUnavailable, ImportError) as error:
            if debug:
                raise
            print(f"{prefix}: error: {_one_line(error)}", file=sys.stderr)
            return 2
        except (ValueError, TypeError, KeyError, OSError, MemoryError, NotImplementedError) as error:
            if debug:
                raise
            print(f"{prefix}: error: {_one_line(error)}", file=sys.stderr)
            return 1
        except KeyboardInterrupt:
            if debug:
                raise
            print(f"{prefix}: interrupted", file=sys.stderr)
            return 130


if __name__ == "__main__":
    sys.exit(main())
