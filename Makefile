# gdbench: `make demo` runs the main job, `make test` runs the test suite.
# Both set up everything that is missing first (scripts/setup.sh) and are quick otherwise.
PY := .venv/bin/python
PYTEST := $(PY) -m pytest

.PHONY: setup demo test test-slow test-all bench lint mutants notebooks

setup:
	@scripts/setup.sh

demo: setup
	$(PY) -m gdbench.app.cli generate "a yellow duck" --preset gd --out runs/duck

# the tests set up without the background build of the banks (scripts/setup.sh): they build what they need
test:
	@GDBENCH_PREBUILD=0 scripts/setup.sh
	$(PY) -m ruff check .
	$(PYTEST) -q -m "not slow" tests

test-slow:
	@GDBENCH_PREBUILD=0 GDBENCH_BROWSER=1 scripts/setup.sh
	$(PYTEST) -q -m "slow" tests

test-all:
	@GDBENCH_PREBUILD=0 GDBENCH_BROWSER=1 scripts/setup.sh
	$(PYTEST) -q tests

bench:
	@GDBENCH_PREBUILD=0 scripts/setup.sh
	$(PY) -m gdbench.refcheck.bm_render --out bench_results/render.csv

lint: setup
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

mutants: setup
	$(PY) scripts/mutants.py

# Executes the four notebooks on the results in GDBENCH_RESULTS (default: the shipped snapshots in
# docs/results; the ablation notebook reads its ablation/ sweep) into runs/notebooks/<name>.ipynb,
# outputs included; the stored notebooks stay without outputs. Every notebook runs; the target
# fails at the end, naming them, if any raised. E.g. make notebooks GDBENCH_RESULTS=bench_results
GDBENCH_RESULTS ?= docs/results
NOTEBOOKS := render_speed error_vs_runtime stability ablation
NOTEBOOKS_OUT := runs/notebooks

notebooks: setup
	@mkdir -p $(NOTEBOOKS_OUT)
	@failed=""; for nb in $(NOTEBOOKS); do \
		echo "notebooks: $$nb.ipynb on $(GDBENCH_RESULTS) -> $(NOTEBOOKS_OUT)/$$nb.ipynb"; \
		GDBENCH_RESULTS="$(abspath $(GDBENCH_RESULTS))" .venv/bin/jupyter execute --timeout=600 \
			--output="$(abspath $(NOTEBOOKS_OUT))/{notebook_name}" notebooks/$$nb.ipynb || failed="$$failed $$nb"; \
	done; \
	if [ -n "$$failed" ]; then echo "notebooks: failed:$$failed"; exit 1; fi
