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
     "setup": callable,                # optional: called before every call of ``run`` and of the peer, untimed
     "info": dict,                     # optional: figures that are not times (bytes on disk), kept in the JSON
     "floor": dict,                    # optional: the work the call must at least do (:func:`floor`)
     "stored_bytes": int | callable}   # optional: bytes of the precomputation the case reads or makes (a
                                       # callable is read after the timed calls)

Every timing is the median of several repeats after one warm-up call (which
absorbs JIT compilation), the repeats of ours and of the peer interleaved;
``setup`` gives each call fresh state outside the timer. Ours and the peer run with the same threads: BLAS through
``threadpoolctl``, numba through ``numba.set_num_threads``. The machine's peak
float64 rate is measured in the same run as the median GFLOP/s of a large
``numpy`` matrix product, and its memory bandwidth as the median GB/s of a
STREAM triad (``a = b + s c``, 24 bytes an element, :func:`measure_bandwidth_gbs`),
both before and after the cases (the larger kept), so ratios hold on a shared, noisy machine.

A case's ``floor`` is the work any implementation of its pass must at least do, counted from the case's
sizes by a formula written next to the case (not measured): FLOPs (a multiply-add counts 2) and bytes that
must cross the memory bus (its stored operands read once, its outputs written once). The report gives its
share of the peak (floor GFLOP / seconds / peak), of the bandwidth (floor GB / seconds / bandwidth) and of
the roofline (``max(flop / peak, bytes / bandwidth) / seconds``: 100% is a pass at the machine's limit).

``write_docs`` writes the tables of a report into a Markdown file between
``<!-- bench:begin NAME -->`` and ``<!-- bench:end NAME -->`` markers (the
section ``machine`` gets the run's header; any other ``NAME`` the cases whose
names start with ``NAME.``, with the rows of an earlier run that this one did not
repeat kept below under their own run line), leaving the text around them as it is.
``python -m prtlab.bench`` runs the benchmarks from the command line.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import functools
import importlib.util
import json
import os
import platform
import re
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

from prtlab._shipped import clone_doc, shipped_folder

__all__ = ["case", "floor", "floor_shares", "run_benchmarks", "measure_peak_gflops", "measure_bandwidth_gbs",
           "benchmark_dir", "render_section", "write_docs", "default_docs_path", "doc_sections", "main", "transfer_csr",
           "check_same_work"]

_CASES: dict[str, Callable] = {}


def case(name: str):
    """Register a benchmark case under ``name`` (dotted, e.g. ``"sh.basis.order4.1M"``)."""

    def register(fn):
        if name in _CASES and _CASES[name].__module__ != fn.__module__:
            raise ValueError(f"benchmark case {name!r} is defined twice")
        _CASES[name] = fn
        return fn

    return register


def floor(flop: float | None = None, nbytes: float | None = None, formula: str = "") -> dict:
    """A case's ``floor``: the FLOPs (multiply-add = 2) and bytes its pass must at least do and move, with the
    ``formula`` they come from (in the case's sizes), for the report. At least one of ``flop``, ``nbytes``."""
    if flop is None and nbytes is None:
        raise ValueError("floor needs flop or nbytes; give the work the pass must at least do")
    for label, value in (("flop", flop), ("nbytes", nbytes)):
        if value is not None and (isinstance(value, bool) or not np.isfinite(value) or value < 0):
            raise ValueError(f"floor {label} must be a finite number >= 0, got {value!r}")
    out = {"formula": str(formula)}
    if flop is not None:
        out["gflop"] = float(flop) / 1e9
    if nbytes is not None:
        out["bytes"] = float(nbytes)
    return out


def floor_shares(entry_floor: dict, seconds: float, peak_gflops: float, bandwidth_gbs: float) -> dict:
    """``share_of_peak``, ``share_of_bandwidth`` and ``share_of_roofline`` of a floor run in ``seconds``."""
    t_flop = entry_floor.get("gflop", 0.0) / peak_gflops
    t_bytes = entry_floor.get("bytes", 0.0) / 1e9 / bandwidth_gbs
    shares = {"share_of_roofline": max(t_flop, t_bytes) / seconds}
    if "gflop" in entry_floor:
        shares["share_of_peak"] = t_flop / seconds
    if "bytes" in entry_floor:
        shares["share_of_bandwidth"] = t_bytes / seconds
    return shares


def benchmark_dir() -> Path:
    """The folder holding ``bench_*.py``: ``$PRTLAB_BENCHMARKS`` if set, else the one shipped in the package."""
    return shipped_folder("PRTLAB_BENCHMARKS", "benchmarks", "benchmark", "bench_*.py files")


def _discover() -> None:
    for path in sorted(benchmark_dir().glob("bench_*.py")):
        module_name = f"prtlab_benchmarks.{path.stem}"
        if module_name in sys.modules:
            continue
        spec = importlib.util.spec_from_file_location(module_name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module
        spec.loader.exec_module(module)


def _time(fns: list[Callable], repeats: int, warmup: bool = True, setup: Callable | None = None) -> list[list[float]]:
    """Seconds of ``repeats`` calls of each of ``fns``, interleaved (ours, peer, ours, peer, ...) so that a
    change of the machine's load during the case weighs on both alike; ``setup`` before every call."""
    if warmup:
        for fn in fns:
            if setup is not None:
                setup()
            fn()  # warm-up: JIT compilation, caches, page faults
    times = [[] for _ in fns]
    for _ in range(repeats):
        for fn, seconds in zip(fns, times):
            if setup is not None:
                setup()
            t0 = time.perf_counter()
            fn()
            seconds.append(time.perf_counter() - t0)
    return times


@contextlib.contextmanager
def _threads(threads: int):
    """BLAS (threadpoolctl) and numba limited to ``threads`` inside the block."""
    from threadpoolctl import threadpool_limits

    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency
        numba = None
    previous = numba.get_num_threads() if numba is not None else None
    with threadpool_limits(threads):
        if numba is not None:
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        try:
            yield
        finally:
            if numba is not None:
                numba.set_num_threads(previous)


def measure_peak_gflops(quick: bool = False) -> float:
    """Median GFLOP/s of a float64 matrix product ``A @ B`` (``2 n^3`` flops) through numpy."""
    n = 1024 if quick else 2048
    rng = np.random.default_rng(0)
    a, b = rng.random((n, n)), rng.random((n, n))
    seconds = statistics.median(_time([lambda: a @ b], 3 if quick else 5)[0])
    return 2.0 * n**3 / seconds / 1e9


@functools.lru_cache(maxsize=1)
def _triad_kernel():
    """The STREAM triad ``a[i] = b[i] + scalar c[i]`` as a parallel numba kernel, compiled once a process."""
    import numba

    @numba.njit(parallel=True, cache=True)
    def triad(a, b, c, scalar):
        for i in numba.prange(a.shape[0]):
            a[i] = b[i] + scalar * c[i]

    return triad


def measure_bandwidth_gbs(quick: bool = False) -> float:
    """Median GB/s of a STREAM triad ``a = b + s c`` over float64 arrays of 256 MiB each (quick: 64 MiB, past the
    2 x 2 MiB of L2 caches this was written on), counted as STREAM does (24 bytes an element: two reads, one
    write), on numba's threads."""
    n = (1 << 23) if quick else (1 << 25)
    triad = _triad_kernel()
    a, b, c = np.zeros(n), np.ones(n), np.full(n, 2.0)
    seconds = statistics.median(_time([lambda: triad(a, b, c, 3.0)], 5 if quick else 10)[0])
    return 24.0 * n / seconds / 1e9


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _check_threads(threads) -> int:
    if threads is None:
        return os.cpu_count() or 1
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise ValueError(f"threads must be an int >= 1, got {threads!r}; give the thread count for ours and the peers")
    return int(threads)


def _entry(name: str, spec: dict, times: list[float], n_repeats: int) -> tuple[dict, str]:
    """The report entry of a case from its spec and the medians ``times`` (ours, then the peer's), and its line
    of output. ``stored_bytes`` may be a callable, read after the timed calls (a precomputation's size)."""
    seconds = times[0]
    entry = {"name": name, "seconds_median": seconds, "repeats": n_repeats}
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
        peer_name, peer_seconds = spec["peer"][0], times[1]
        entry["peer"] = {"name": peer_name, "seconds_median": peer_seconds}
        entry["speedup_vs_peer"] = peer_seconds / seconds
        line += f"  peer {peer_name}: {peer_seconds * 1e3:.2f} ms (x{peer_seconds / seconds:.2f})"
    if spec.get("floor"):
        entry["floor"] = dict(spec["floor"])
        line += "  floor " + ", ".join(f"{v:.3g} {k}" for k, v in entry["floor"].items() if k != "formula")
    stored = spec.get("stored_bytes")
    stored = stored() if callable(stored) else stored
    if stored is not None:
        entry["stored_bytes"] = int(stored)
        line += f"  stored {entry['stored_bytes'] / 1e6:.4g} MB"
    if spec.get("info"):
        entry["info"] = dict(spec["info"])
        line += "  " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                 for k, v in entry["info"].items())
    return entry, line


def run_benchmarks(quick: bool = False, select: str | None = None, json_path=None, out=print,
                   threads: int | None = None) -> dict:
    """Run every registered case (or those whose name contains ``select``).

    Ours and every peer run with ``threads`` threads (default: every core), BLAS and numba alike.
    Returns the report ``{"machine": {cpu, cores, threads, peak_gflops, bandwidth_gbs, numpy, python}, "quick":
    bool, "started": ISO date (UTC), "load_at_start": [1, 5, 15 min load averages], "registered": [every case's
    name], "cases": [...]}``, one entry
    per case (``name``, ``seconds_median``, ``repeats`` and, where known, ``gflop``, ``gflops``,
    ``share_of_peak``, ``items``, ``items_per_second``, ``peer``, ``speedup_vs_peer``, ``floor`` (``gflop``,
    ``bytes``, ``formula``, ``share_of_peak``, ``share_of_bandwidth``, ``share_of_roofline``),
    ``stored_bytes``, ``info``), and
    writes it to ``json_path`` as JSON if given.
    """
    threads = _check_threads(threads)
    _discover()
    names = sorted(n for n in _CASES if select is None or select in n)
    if not names:
        raise ValueError(f"no benchmark case matches {select!r}; cases: {sorted(_CASES)}")
    started = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    load = [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None
    repeats = 3 if quick else 7
    cases = []
    with _threads(threads):
        peak_before, bandwidth_before = measure_peak_gflops(quick), measure_bandwidth_gbs(quick)
        out(f"machine peak (float64 matmul, {threads} threads): {peak_before:.1f} GFLOP/s, bandwidth (triad) "
            f"{bandwidth_before:.1f} GB/s; load at start {load}")
        for name in names:
            spec = _CASES[name](quick)
            n_repeats = min(repeats, int(spec.get("repeats", repeats)))
            warmup, setup = spec.get("warmup", True), spec.get("setup")
            fns = [spec["run"]] + ([spec["peer"][1]] if spec.get("peer") else [])
            times = [statistics.median(t) for t in _time(fns, n_repeats, warmup, setup)]
            entry, line = _entry(name, spec, times, n_repeats)
            out(line)
            cases.append(entry)
        peak = max(peak_before, measure_peak_gflops(quick))
        bandwidth = max(bandwidth_before, measure_bandwidth_gbs(quick))
    for entry in cases:
        if "gflops" in entry:
            entry["share_of_peak"] = entry["gflops"] / peak
        if "floor" in entry:
            entry["floor"].update(floor_shares(entry["floor"], entry["seconds_median"], peak, bandwidth))
    report = {
        "machine": {
            "cpu": _cpu_name(),
            "cores": os.cpu_count(),
            "threads": threads,
            "peak_gflops": peak,
            "bandwidth_gbs": bandwidth,
            "numpy": np.__version__,
            "python": platform.python_version(),
        },
        "quick": quick,
        "started": started,
        "load_at_start": load,
        "registered": sorted(_CASES),
        "cases": cases,
    }
    if json_path:
        Path(json_path).write_text(json.dumps(report, indent=2))
        out(f"wrote {json_path}")
    return report


# --------------------------------------------------------------------------- peers


def transfer_csr(sparse):
    """A :class:`prtlab.wavelet.SparseTransfer` decoded once into a ``scipy.sparse`` CSR matrix ``(V, 2 T)``
    float64 (``T = 6 r^2``; a pulse vertex's entries in columns ``[0, T)``, a Haar vertex's in ``[T, 2 T)``),
    so that ``csr @ [light_pulse; light_haar]`` (``(2 T, C)``) is ``sparse.dot(light_pulse, light_haar)``: the
    peer a user would pick for a per-frame sparse product."""
    import scipy.sparse

    n = 6 * sparse.res * sparse.res
    raw = sparse.indices.astype(np.int64)
    rows = np.repeat(np.arange(sparse.n_vertices), np.diff(sparse.indptr))
    values = np.where(raw >= sparse.sign_bit, -1.0, 1.0) * sparse.codes * (sparse.scale.astype(np.float64)[rows] / 255)
    columns = (raw & (sparse.sign_bit - 1)) + n * (sparse.basis[rows] == sparse.HAAR)
    return scipy.sparse.csr_matrix((values, columns, sparse.indptr), shape=(sparse.n_vertices, 2 * n))


def check_same_work(ours, peer, name: str, rtol: float = 1e-9, atol: float = 1e-12) -> None:
    """Raise ``RuntimeError`` unless a case's result and its peer's agree (the peer does the same work)."""
    ours, peer = np.asarray(ours, float), np.asarray(peer, float)
    if ours.shape != peer.shape or not np.allclose(ours, peer, rtol=rtol, atol=atol):
        err = np.max(np.abs(ours - peer)) if ours.shape == peer.shape else f"shapes {ours.shape} / {peer.shape}"
        raise RuntimeError(f"benchmark {name}: the peer's result differs from ours (max |diff| {err}); "
                           "the peer must do the same work")


# --------------------------------------------------------------------------- generated docs

_MARKER = re.compile(r"<!-- bench:begin (?P<name>[\w.-]+) -->\n(?P<body>.*?)<!-- bench:end (?P=name) -->", re.S)


def default_docs_path() -> Path:
    """``docs/BENCHMARKS.md`` of the checkout holding this package."""
    return clone_doc("BENCHMARKS.md")


def _ms(seconds: float) -> str:
    ms = seconds * 1e3
    if seconds >= 100:  # a whole precomputation
        return f"{seconds / 60:.1f} min"
    return f"{ms:.3g} ms" if ms < 100 else f"{ms:.0f} ms"


def _mb(nbytes: float) -> str:
    return f"{nbytes / 1e6:.3g} MB"


def _floor_cells(entry_floor: dict | None) -> list[str]:
    """The floor's work (``GFLOP, MB``, ``-`` where not counted) and its shares (``peak, bandwidth, roofline``)."""
    if not entry_floor:
        return ["", ""]
    work = ", ".join([f"{entry_floor['gflop']:.3g}" if "gflop" in entry_floor else "-",
                      f"{entry_floor['bytes'] / 1e6:.3g}" if "bytes" in entry_floor else "-"])
    shares = ", ".join(f"{100 * entry_floor[k]:.2g}%" if k in entry_floor else "-"
                       for k in ("share_of_peak", "share_of_bandwidth", "share_of_roofline"))
    return [work, shares]


def _info_text(info: dict) -> str:
    return ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in info.items())


def _bandwidth_text(machine: dict) -> str:
    return f", bandwidth {machine['bandwidth_gbs']:.1f} GB/s (STREAM triad)" if "bandwidth_gbs" in machine else ""


def _run_line(report: dict) -> str:
    m = report["machine"]
    load = report.get("load_at_start")
    load_text = "unknown" if load is None else " / ".join(f"{x:.2f}" for x in load)
    return (f"Run of {report.get('started', 'an unknown date')}, {'quick' if report['quick'] else 'full'} sizes, "
            f"{m['threads'] if 'threads' in m else m['cores']} threads for ours and the peers, load average at the "
            f"start {load_text} (1 / 5 / 15 min) on {m['cores']} cores; float64 peak {m['peak_gflops']:.1f} GFLOP/s "
            f"(numpy matmul){_bandwidth_text(m)}, measured in the same run. {m['cpu']}, numpy {m['numpy']}, "
            f"Python {m['python']}.")


_TABLE_HEAD = ("| case | median | peer | peer median | peer / ours | GFLOP/s (share of peak) | floor: GFLOP, MB | "
               "floor's share: peak, bandwidth, roofline | stored | items/s | info |",
               "|---|---|---|---|---|---|---|---|---|---|---|")
_ROW_NAME = re.compile(r"^\| `(?P<name>[^`]+)` \|")


def _earlier_rows(body: str, report: dict) -> str:
    """The tables of a section's earlier text (``body``) cut to the rows of the cases ``report`` did not run and
    that are still registered, each block with its own run line; ``""`` when no row is left."""
    ran = {c["name"] for c in report["cases"]}
    registered = set(report.get("registered", ()))
    out, rows = [], []
    for line in body.splitlines():
        row = _ROW_NAME.match(line)
        if row and row["name"] not in ran and (not registered or row["name"] in registered):
            rows.append(line)
        elif line.startswith("Run of "):
            if rows:
                out.append("\n".join([*_TABLE_HEAD, *rows]) + "\n\n" + line + "\n")
            rows = []
    return "".join("\n" + block for block in out)


def render_section(report: dict, name: str) -> str | None:
    """The Markdown of section ``name`` from a report (``run_benchmarks``' value or its JSON), or None when
    the report has no case for it: ``machine`` is the run's header line, any other name a table of the
    cases named ``NAME.*`` (median, peer, peer median, ratio peer / ours, GFLOP/s and share of the peak, the
    floor's GFLOP and MB and their shares of peak, bandwidth and roofline, stored MB, throughput, info)
    followed by the run's line."""
    if name == "machine":
        return _run_line(report) + "\n"
    rows = [c for c in report["cases"] if c["name"] == name or c["name"].startswith(name + ".")]
    if not rows:
        return None
    lines = list(_TABLE_HEAD)
    for c in rows:
        peer = c.get("peer")
        rate = f"{c['gflops']:.3g} ({100 * c['share_of_peak']:.1f}%)" if "share_of_peak" in c else ""
        lines.append("| " + " | ".join([
            f"`{c['name']}`", _ms(c["seconds_median"]), peer["name"] if peer else "",
            _ms(peer["seconds_median"]) if peer else "",
            f"x{c['speedup_vs_peer']:.2f}" if peer else "", rate, *_floor_cells(c.get("floor")),
            _mb(c["stored_bytes"]) if "stored_bytes" in c else "",
            f"{c['items_per_second']:.3g}" if "items_per_second" in c else "",
            _info_text(c["info"]) if c.get("info") else ""]).replace("\n", " ") + " |")
    return "\n".join(lines) + "\n\n" + _run_line(report) + "\n"


def write_docs(report: dict, path=None) -> list[str]:
    """Write the tables of ``report`` into the marked sections of ``path`` (default :func:`default_docs_path`)
    that it has cases for; the text outside the markers is kept. A section's rows of cases the report did not run
    (a ``--select`` run) stay below its new table, with the run line they came with, unless the case is no longer
    registered. Returns the names written.

    Raises ``FileNotFoundError`` when ``path`` does not exist and ``ValueError`` when it has no markers.
    """
    path = Path(path) if path is not None else default_docs_path()
    write_docs_check(path)
    text = path.read_text()
    written = []

    def replace(match):
        body = render_section(report, match["name"])
        if body is None:
            return match[0]
        if match["name"] != "machine":
            body += _earlier_rows(match["body"], report)
        written.append(match["name"])
        return f"<!-- bench:begin {match['name']} -->\n{body}<!-- bench:end {match['name']} -->"

    path.write_text(_MARKER.sub(replace, text))
    return written


def doc_sections(text: str) -> dict[str, str]:
    """``{NAME: text between the markers}`` of a Markdown text."""
    return {m["name"]: m["body"] for m in _MARKER.finditer(text)}


def main(argv=None) -> int:
    """``python -m prtlab.bench [--quick] [--select NAME] [--json FILE] [--threads N] [--write-docs [PATH]]``."""
    parser = argparse.ArgumentParser(prog="python -m prtlab.bench", description=main.__doc__)
    add_arguments(parser)
    return run_from_args(parser.parse_args(argv))


def add_arguments(parser) -> None:
    """The options of ``prtlab bench`` on an argparse parser."""
    parser.add_argument("--quick", action="store_true", help="small sizes")
    parser.add_argument("--json", type=Path, default=None, help="also write the results to this JSON file")
    parser.add_argument("--select", default=None, help="run only cases whose name contains this")
    parser.add_argument("--threads", type=int, default=None, help="threads for ours and the peers (default: all)")
    parser.add_argument("--write-docs", nargs="?", type=Path, const=default_docs_path(), default=None,
                        metavar="PATH", help="write the tables into the marked sections of PATH "
                                             "(default docs/BENCHMARKS.md of the checkout)")


def run_from_args(args) -> int:
    """Run ``prtlab bench`` from parsed :func:`add_arguments` options; the docs file is checked first."""
    if args.write_docs is not None:
        write_docs_check(args.write_docs)
    report = run_benchmarks(quick=args.quick, select=args.select, json_path=args.json, threads=args.threads)
    if args.write_docs is not None:
        names = write_docs(report, args.write_docs)
        print(f"wrote sections {', '.join(names) or '(none)'} of {args.write_docs}")
    return 0


def write_docs_check(path) -> None:
    """The checks of :func:`write_docs` on ``path`` before any benchmark runs."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--write-docs {path}: no such file; give a Markdown file with "
                                "<!-- bench:begin NAME --> / <!-- bench:end NAME --> markers")
    if not _MARKER.search(path.read_text()):
        raise ValueError(f"--write-docs {path}: no <!-- bench:begin NAME --> ... <!-- bench:end NAME --> "
                         "section; add the markers where the tables go")


if __name__ == "__main__":  # pragma: no cover
    from prtlab.bench import main as _main  # the cases register with the imported module, not with __main__

    sys.exit(_main())
