"""The fidelity tier: whole scenes against Mitsuba 3 (or prtlab's own Monte Carlo), scored with
:func:`prtlab.compare` on every object and on direct / indirect / total.

Rules every module here follows:

- every test is marked ``fidelity`` (this conftest marks every item it collects), so ``make test``
  leaves them out and ``make fidelity`` (run by CI after ``make test``) runs them;
- goals are the papers' figures or derived bounds, never our own output; a goal is met when
  ``rel_rms <= hypot(goal, noise)`` (:meth:`prtlab.metrics.ComparisonRow.meets`), and references are
  sampled so their relative noise is at most a third of the goal (:meth:`prtlab.metrics.Comparison.check`
  refuses a noisier one);
- where a paper's method cannot reach a goal, the case is a strict xfail whose reason gives the
  measured figure and its cause;
- expensive references and precomputations are module-scoped fixtures in an ``xdist_group``, so one
  worker computes each once; the whole tier stays within about 20 minutes on 2 cores.
"""

from __future__ import annotations

import pytest


def pytest_collection_modifyitems(config, items):
    for item in items:
        if "tests/fidelity/" in str(item.fspath).replace("\\", "/"):
            item.add_marker(pytest.mark.fidelity)
