# dotshell — set-up and everyday commands. `make demo` and `make test` work on a fresh machine.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test docs bench validate clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	touch $(STAMP)

## demo: create the venv, install, and run a full 360° scan of the simulated metal cylinder
demo: $(STAMP)
	$(VENV)/bin/dotshell scan profiles/sim-metal-cylinder.toml --out runs

## test: the test suite (reduced resolutions; a few minutes on 2 cores). Two worker processes,
## a test file per worker at a time (module fixtures are built once), the longest files first,
## each on one BLAS/OpenMP thread so the two share the cores instead of oversubscribing them;
## the numba kernels are compiled once, in the background while the workers run the files
## that call none; the others wait for them (tests/conftest.py, tests/compile_kernels.py).
## TEST_WORKERS=0: one process.
TEST_WORKERS ?= 2
test: $(STAMP)
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 $(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

## docs: the documentation site from docs/ (MkDocs, offline, warnings are errors) into site/
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet

## bench: speed and memory figures against peers measured in the same run
bench: $(STAMP)
	$(PY) benchmarks/run.py
	$(PY) benchmarks/devices.py
	$(PY) benchmarks/frame_checks.py

## validate: full-resolution accuracy checks, then the codings x PDI table (docs/light-model.md)
validate: $(STAMP)
	$(PY) -m pytest -q -s -m slow tests
	$(PY) benchmarks/validate_matrix.py

clean:
	rm -rf $(VENV) .venv-bench-contrib runs .pytest_cache site
