"""One line on stderr when numba compiles a kernel: the first run after install pays, and says so.

Every prtlab kernel is compiled with ``cache=True``, so numba compiles it once per machine (and per
change of its source) and later processes load the machine code from disk. Loading from the disk
cache fires no event; only a real compilation broadcasts numba's ``"numba:compile"`` event
(:mod:`numba.core.event`). :func:`install` registers a listener that prints :data:`MESSAGE` on the
first such event of the process for a prtlab function (not for the user's own numba code) and stays
silent afterwards. It is installed lazily by the entry
points (:mod:`prtlab.api`, the ``prtlab`` command), so ``import prtlab`` does not import numba.
"""

from __future__ import annotations

import contextlib
import sys

__all__ = ["MESSAGE", "install", "suppressed"]

MESSAGE = "prtlab: compiling numba kernels for this machine (first run only; cached afterwards)"

_state = {"installed": False, "announced": False, "suppressed": 0}


def _is_prtlab(dispatcher) -> bool:
    module = getattr(getattr(dispatcher, "py_func", None), "__module__", None) or ""
    return module == "prtlab" or module.startswith("prtlab.")


def _announce(dispatcher) -> None:
    if _state["announced"] or _state["suppressed"] or not _is_prtlab(dispatcher):
        return
    _state["announced"] = True
    from tqdm import tqdm

    tqdm.write(MESSAGE, file=sys.stderr)  # on its own line, above any progress bar


def install() -> None:
    """Register the compile listener (once per process; later calls do nothing)."""
    if _state["installed"]:
        return
    from numba.core import event

    class _CompileNotice(event.Listener):
        def on_start(self, ev):
            _announce(ev.data.get("dispatcher") if isinstance(ev.data, dict) else None)

        def on_end(self, ev):
            pass

    event.register("numba:compile", _CompileNotice())
    _state["installed"] = True


@contextlib.contextmanager
def suppressed():
    """Within this block, compilations print nothing (``prtlab -q``)."""
    _state["suppressed"] += 1
    try:
        yield
    finally:
        _state["suppressed"] -= 1
