"""The benchmark runner behind ``prtlab bench``.

Cases live in ``bench_*.py`` files of the package's ``prtlab/benchmarks/`` folder
(shown as ``benchmarks/`` at the root of a clone), or of the folder named by
``PRTLAB_BENCHMARKS``. A case is a function decorated with
:func:`case`; it takes ``quick`` and returns a dict::

    {"run": callable,                  # the work, called with no arguments
     "gflop": float | None,            # floating-point work of one call, in GFLOP
     "items": int | None,              # items (directions, rays, vertices) per call
     "peer": (name, callable) | None,  # the same work done by a peer, timed in the same run
     "repeats": int,                   # optional: fewer repeats for a long case (a precomputation)
     "warmup": bool,                   # optional: False skips the warm-up call (kernels compiled already)
     "info": dict}                     # optional: figures that are not times (bytes on disk), kept in the JSON

Every timing is the median of several repeats after one warm-up call (which
absorbs JIT compilation). The machine's peak float64 rate is measured in the
same run as the median GFLOP/s of a large ``numpy`` matrix product, before and
after the cases (the larger is kept), so ratios hold on a shared, noisy machine.
"""

from __future__ import annotations

import importlib.util
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

__all__ = ["case", "run_benchmarks", "measure_peak_gflops", "benchmark_dir"]

_CASES: dict[str, Callable] = {}


def case(name: str):
    """Register a benchmark case under ``name`` (dotted, e.g. ``"sh.basis.order4.1M"``)."""

    def register(fn):
        if name in _CASES and _CASES[name].__module__ != fn.__module__:
            raise ValueError(f"benchmark case {name!r} is defined twice")
        _CASES[name] = fn
        return fn

    return register


def benchmark_dir() -> Path:
    """The folder holding ``bench_*.py``: ``$PRTLAB_BENCHMARKS`` if set, else the one shipped in the package."""
    env = os.environ.get("PRTLAB_BENCHMARKS")
    folder = Path(env) if env else Path(__file__).resolve().parent / "benchmarks"
    if not folder.is_dir():
        where = "PRTLAB_BENCHMARKS names" if env else "the installed prtlab package has"
        raise FileNotFoundError(
            f"no benchmark folder at {folder} ({where} none); set PRTLAB_BENCHMARKS to a folder of "
            "bench_*.py files or reinstall prtlab"
        )
    return folder


def _discover() -> None:
    for path in sorted(benchmark_dir().glob("bench_*.py")):
        module_name = f"prtlab_benchmarks.{path.stem}"
        if module_name in sys.modules:
            continue
        spec = importlib.util.spec_from_file_location(module_name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module
        spec.loader.exec_module(module)


def _time(fn: Callable, repeats: int, warmup: bool = True) -> list[float]:
    if warmup:
        fn()  # warm-up: JIT compilation, caches, page faults
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def measure_peak_gflops(quick: bool = False) -> float:
    """Median GFLOP/s of a float64 matrix product ``A @ B`` (``2 n^3`` flops) through numpy."""
    n = 1024 if quick else 2048
    rng = np.random.default_rng(0)
    a, b = rng.random((n, n)), rng.random((n, n))
    seconds = statistics.median(_time(lambda: a @ b, 3 if quick else 5))
    return 2.0 * n**3 / seconds / 1e9


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def run_benchmarks(quick: bool = False, select: str | None = None, json_path=None, out=print) -> dict:
    """Run every registered case (or those whose name contains ``select``).

    Returns the report ``{"machine": {cpu, cores, peak_gflops, numpy, python}, "quick": bool,
    "cases": [...]}``, one entry per case (``name``, ``seconds_median`` and, where known,
    ``gflop``, ``gflops``, ``share_of_peak``, ``items``, ``items_per_second``, ``peer``,
    ``speedup_vs_peer``, ``info``), and writes it to ``json_path`` as JSON if given.
    """
    _discover()
    names = sorted(n for n in _CASES if select is None or select in n)
    if not names:
        raise ValueError(f"no benchmark case matches {select!r}; cases: {sorted(_CASES)}")
    repeats = 3 if quick else 7
    peak_before = measure_peak_gflops(quick)
    out(f"machine peak (float64 matmul): {peak_before:.1f} GFLOP/s")
    cases = []
    for name in names:
        spec = _CASES[name](quick)
        n_repeats = min(repeats, int(spec.get("repeats", repeats)))
        seconds = statistics.median(_time(spec["run"], n_repeats, spec.get("warmup", True)))
        entry = {"name": name, "seconds_median": seconds}
        gflop = spec.get("gflop")
        if gflop:
            entry["gflop"] = gflop
            entry["gflops"] = gflop / seconds
        if spec.get("items"):
            entry["items"] = int(spec["items"])
            entry["items_per_second"] = spec["items"] / seconds
        line = f"{name:40s} {seconds * 1e3:10.2f} ms"
        if "items_per_second" in entry:
            line += f"  {entry['items_per_second']:.3g} items/s"
        if spec.get("peer"):
            peer_name, peer_fn = spec["peer"]
            peer_seconds = statistics.median(_time(peer_fn, n_repeats, spec.get("warmup", True)))
            entry["peer"] = {"name": peer_name, "seconds_median": peer_seconds}
            entry["speedup_vs_peer"] = peer_seconds / seconds
            line += f"  peer {peer_name}: {peer_seconds * 1e3:.2f} ms (x{peer_seconds / seconds:.2f})"
        if spec.get("info"):
            entry["info"] = dict(spec["info"])
            line += "  " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                     for k, v in entry["info"].items())
        out(line)
        cases.append(entry)
    peak = max(peak_before, measure_peak_gflops(quick))
    for entry in cases:
        if "gflops" in entry:
            entry["share_of_peak"] = entry["gflops"] / peak
    report = {
        "machine": {
            "cpu": _cpu_name(),
            "cores": os.cpu_count(),
            "peak_gflops": peak,
            "numpy": np.__version__,
            "python": platform.python_version(),
        },
        "quick": quick,
        "cases": cases,
    }
    if json_path:
        Path(json_path).write_text(json.dumps(report, indent=2))
        out(f"wrote {json_path}")
    return report
