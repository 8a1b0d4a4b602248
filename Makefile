# Two entry points for a fresh machine with only Python 3.11 and make: `make demo` and `make test`.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# One BLAS/OpenMP thread: labcal's matrices are small, and oversubscribed BLAS threads slow fits 100x on 2 cores.
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1

.PHONY: install demo test lint contracts pytest pytest-suite pytest-acceptance bench clean

$(STAMP): pyproject.toml fakes/pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	# CPU build first: a bare `torch` requirement would pull a multi-GB CUDA build on this machine.
	$(BIN)/python -m pip install --quiet "torch==2.13.0"
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	# The test doubles (fakes/, their own distribution): after labcal, which they require and which is not on PyPI.
	$(BIN)/python -m pip install --quiet -e fakes
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/labcal demo

lint: $(STAMP)
	$(BIN)/ruff check src fakes/src tests benchmarks
	$(BIN)/ruff format --check src fakes/src tests benchmarks
	$(BIN)/mypy

contracts: $(STAMP)
	$(BIN)/lint-imports

# The bad-input acceptance cases (tests/acceptance) spend most of their time in `labcal` processes of their own;
# they run beside the rest of the suite, one per core, each target's output printed whole when it ends.
pytest: $(STAMP)
	$(MAKE) --no-print-directory -j2 --output-sync=target pytest-suite pytest-acceptance

pytest-suite: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider --ignore=tests/acceptance

pytest-acceptance: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider tests/acceptance

test: lint contracts pytest

bench: $(STAMP)
	$(BIN)/python benchmarks/speed.py

clean:
	rm -rf $(VENV) build src/*.egg-info fakes/build fakes/src/*.egg-info
