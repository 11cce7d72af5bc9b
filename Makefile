# gdbench: `make demo` runs the main job, `make test` runs the test suite.
# Both set up everything that is missing first (scripts/setup.sh) and are quick otherwise.
PY := .venv/bin/python
PYTEST := $(PY) -m pytest

.PHONY: setup demo test test-slow test-all bench lint mutants

setup:
	@scripts/setup.sh

demo: setup
	$(PY) -m gdbench.cli generate "a yellow duck" --preset gd --out runs/duck

test: setup
	$(PY) -m ruff check .
	$(PYTEST) -q -m "not slow" tests

test-slow: setup
	$(PYTEST) -q -m "slow" tests

test-all: setup
	$(PYTEST) -q tests

bench: setup
	$(PY) -m gdbench.bench.bm_render --out bench_results/render.csv

lint: setup
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

mutants: setup
	$(PY) scripts/mutants.py
