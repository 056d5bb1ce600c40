# mst: every target creates what it needs (system libraries, venv, install from the lock file).
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.mst-installed
DEMO_OUT ?= demo-out
LOCK := requirements.lock
# the lock is resolved for the documented target: Debian bookworm (glibc 2.36), CPython 3.11, x86-64
LOCK_PLATFORM ?= x86_64-manylinux_2_36
LOCK_PYTHON ?= 3.11
UV_VERSION ?= 0.13.9

.PHONY: setup warmup demo test test-latest test-all bench lint lock clean

# the numba kernels and their ahead-of-time extensions: warmed again when a kernel source (or what the
# extensions' hash covers) changes, so a pulled checkout does not fall back to the JIT at every start
WARM := $(VENV)/.mst-kernels
# (every *kernels.py module, so that a new one needs no entry here, and the modules they import)
KERNEL_SRC := $(wildcard core/*kernels.py eval/*/*kernels.py meshtools/*kernels.py pipeline/*kernels.py \
	pipeline/*/*kernels.py core/aot.py eval/c2m/warmup.py meshtools/compiled.py pipeline/tracking/covariance.py)

setup: $(WARM)

$(STAMP): pyproject.toml $(LOCK) .ci/setup
	PYTHON=$(PYTHON) VENV=$(VENV) bash .ci/setup
	@touch $(STAMP)

$(WARM): $(STAMP) $(KERNEL_SRC)
	$(BIN)/python -m mst.eval.c2m.warmup
	@touch $(WARM)

## warmup: compile the numba kernels of mst c2m, convert-model and mst track into their on-disk cache, and the c2m,
## convert-model and edge-tracker kernels ahead of time for this CPU (mst.core.aot; make setup does it once;
## every later process only loads them)
warmup: $(STAMP)
	$(BIN)/python -m mst.eval.c2m.warmup
	@touch $(WARM)

## demo: the whole chain on the bundled sample (samples/), results in $(DEMO_OUT)/
demo: $(WARM)
	PATH=$(CURDIR)/$(BIN):$$PATH OUT=$(DEMO_OUT) bash samples/demo.sh

## test: the default suite on the locked versions (slow tests excluded; `make bench` covers them).
## Exit 5 (no tests) fails. This is what CI (.ci/run) runs. Bytecode is written (__pycache__, ignored by
## git) even where PYTHONDONTWRITEBYTECODE is set: the suite's subprocesses then load mst's modules
## instead of compiling them again (~0.1-0.3 s CPU each).
## The suite runs on every core (pytest-xdist, one test file per worker: a file's module fixtures are
## built once): 2 cores 222 s -> ~110 s.
test: $(WARM)
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -q -n auto --dist loadfile

## test-latest: the same suite on the newest versions pyproject.toml allows (in .venv-latest), to test upgrades on purpose
test-latest:
	PYTHON=$(PYTHON) VENV=.venv-latest MST_LATEST=1 bash .ci/setup
	.venv-latest/bin/python -m pytest -q

test-all: $(WARM)
	$(BIN)/python -m pytest -q -m ''

## bench: speed and memory of every stage, written to bench-results.json
bench: $(WARM)
	$(BIN)/python -m mst.eval.bench --out bench-results.json

lint: $(STAMP)
	$(BIN)/python -m ruff check .

## lock: re-resolve requirements.lock (exact versions + sha256 hashes) from pyproject.toml with uv
lock:
	@test -x .venv-uv/bin/uv || ($(PYTHON) -m venv .venv-uv && .venv-uv/bin/python -m pip install -q uv==$(UV_VERSION))
	.venv-uv/bin/uv pip compile pyproject.toml --extra test --extra dev --generate-hashes \
	    --python-version $(LOCK_PYTHON) --python-platform $(LOCK_PLATFORM) --custom-compile-command "make lock" --upgrade -o $(LOCK)
	@echo "$(LOCK) written; run 'make test' to install and test it"

clean:
	rm -rf $(VENV) .venv-latest .venv-uv $(DEMO_OUT) .pytest_cache bench-results.json
