# Two commands for a newcomer: `make demo` and `make test`. Each builds .venv itself.
# `make test` runs everything (what CI runs) on both cores; `make check` leaves out the slow
# end-to-end runs for the inner loop; `make lint` is ruff's check and format check, then mypy.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test check lint bench venv clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/run-cell --dry-run

test: $(STAMP)
	$(PY) -m pytest -n 2

check: $(STAMP)
	$(PY) -m pytest -n 2 -m "not slow"

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

bench: $(STAMP)
	$(PY) scripts/bench_detection.py
	$(PY) scripts/bench_calibration.py
	$(PY) scripts/bench_parts.py
	$(PY) scripts/bench_drift.py
	$(PY) scripts/bench_annotate.py

clean:
	rm -rf $(VENV) build *.egg-info .mypy_cache
