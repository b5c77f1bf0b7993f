# Two commands for a newcomer: `make demo` and `make test`. Each builds .venv itself.
# `make test` runs everything (what CI runs) on both cores; `make check` leaves out the slow
# end-to-end runs for the inner loop; `make lint` is ruff's check and format check, then mypy.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
TEST_STAMP := $(VENV)/.installed-test

.PHONY: demo test check lint bench venv clean

# pyproject.toml's dependencies as two lines, read by the system Python (3.11+: tomllib) before pip runs
define LIST_DEPENDENCIES
import re, tomllib
project = tomllib.load(open("pyproject.toml", "rb"))["project"]
names = lambda deps: ", ".join(re.split(r"[<>=~!\[ ;]", d, maxsplit=1)[0] for d in deps)
print("      the cell:", names(project["dependencies"]))
print("      the tests:", names(project["optional-dependencies"]["test"]))
endef
export LIST_DEPENDENCIES

# GenICam cameras need Aravis's typelib and what PyGObject builds against (Debian: gir1.2-aravis-0.8,
# libgirepository1.0-dev, libcairo2-dev, pkg-config); without them the genicam extra is left out and
# `make demo`/`make test` work as before (the GenICam tests skip, saying why).
GENICAM_LIBS := pkg-config --exists gobject-introspection-1.0 cairo 2>/dev/null \
	&& ls /usr/lib/*/girepository-1.0/Aravis-0.8.typelib >/dev/null 2>&1

# The first run sets up .venv (about a minute): a line per step before it starts, pip's own output quiet.
# The cell alone (what a line PC runs, and `make demo`): its dependencies, no test tools. `make test`,
# `check`, `lint` and `bench` add the [test] extra (pytest, Playwright, mypy, ruff ...) on top.
$(STAMP): pyproject.toml
	@echo "setting up $(VENV), once: a Python environment with the cell and its dependencies (pyproject.toml)"
	@echo "[1/3] creating $(VENV) with $(PYTHON)"
	@$(PYTHON) -m venv $(VENV)
	@echo "[2/3] updating pip in $(VENV)"
	@$(PY) -m pip install --quiet --progress-bar off --upgrade pip
	@echo "[3/3] installing the cell and what it needs (a minute or so; longer without pip's cache):"
	@$(PYTHON) -c "$$LIST_DEPENDENCIES" | head -1
	@$(PY) -m pip install --quiet --progress-bar off -e .
	@if $(GENICAM_LIBS); then \
		echo "      GenICam cameras: PyGObject (the system has Aravis and gobject-introspection; 20 s to build)"; \
		$(PY) -m pip install --quiet --progress-bar off -e '.[genicam]' \
			|| echo "      GenICam cameras: PyGObject did not install; genicam: sources and their tests are off"; \
	else \
		echo "      GenICam cameras: off (no Aravis or gobject-introspection here: docs/cameras.md says what to install)"; \
	fi
	@touch $(STAMP)
	@echo "$(VENV) is ready"

$(TEST_STAMP): $(STAMP)
	@echo "adding the test tools to $(VENV), once (pyproject.toml's [test] extra):"
	@$(PYTHON) -c "$$LIST_DEPENDENCIES" | tail -1
	@$(PY) -m pip install --quiet --progress-bar off -e '.[test]'
	@touch $(TEST_STAMP)

venv: $(STAMP)

demo: $(STAMP)
	@echo "make demo: run-cell --dry-run (the simulated cell clears a table; see README)"
	@$(VENV)/bin/run-cell --dry-run

test: $(TEST_STAMP)
	@echo "make test: the whole suite on both cores (pytest -n 2)"
	@$(PY) -m pytest -n 2

check: $(TEST_STAMP)
	$(PY) -m pytest -n 2 -m "not slow"

lint: $(TEST_STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

bench: $(TEST_STAMP)
	$(PY) scripts/bench_detection.py
	$(PY) scripts/bench_calibration.py
	$(PY) scripts/bench_parts.py
	$(PY) scripts/bench_drift.py
	$(PY) scripts/bench_annotate.py

clean:
	rm -rf $(VENV) build *.egg-info .mypy_cache
