# prtlab — every target creates .venv and installs what it needs on first use (no root needed:
# install-llvm.sh only adds Mitsuba's LLVM library when run as root). Without make: pip install ".[reference]".
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test fidelity test-slow bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test,reference,distributed]"
	-@bash .ci/install-llvm.sh
	touch $(STAMP)

# Reproduce every figure and table that exists so far, in quick mode, into report/.
demo: $(STAMP)
	PRTLAB_QUICK=1 $(VENV)/bin/prtlab reproduce --quick --out report
	@echo "open report/index.html"

# The default test run: unit and property tests, notebooks in quick mode. Under 15 min on 2 cores.
test: $(STAMP)
	PRTLAB_QUICK=1 $(PY) -m pytest -n 2 --dist loadgroup -m "not slow and not fidelity" --nbmake tests $(wildcard notebooks/*.ipynb)

# The fidelity tier: each pipeline on its paper's scenes at reduced size against Mitsuba 3 / Monte Carlo,
# every object, direct / indirect / total, moved objects where the method allows motion.
fidelity: $(STAMP)
	PRTLAB_QUICK=1 $(PY) -m pytest -n 2 --dist loadgroup -m fidelity tests/fidelity

test-slow: $(STAMP)
	$(PY) -m pytest -n 2 -m slow tests

bench: $(STAMP)
	$(VENV)/bin/prtlab bench --json bench.json --write-docs

clean:
	rm -rf $(VENV) report .pytest_cache .hypothesis
