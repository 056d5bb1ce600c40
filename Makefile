# mst: every target creates what it needs (system libraries, venv, editable install).
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.mst-installed
DEMO_OUT ?= demo-out

.PHONY: setup demo test test-all bench lint clean

setup: $(STAMP)

$(STAMP): pyproject.toml .ci/setup
	PYTHON=$(PYTHON) VENV=$(VENV) bash .ci/setup
	@touch $(STAMP)

## demo: the whole chain on the bundled sample (samples/), results in $(DEMO_OUT)/
demo: $(STAMP)
	PATH=$(CURDIR)/$(BIN):$$PATH OUT=$(DEMO_OUT) bash samples/demo.sh

## test: the default suite (slow tests excluded; `make bench` covers them). Exit 5 (no tests) fails.
test: $(STAMP)
	$(BIN)/python -m pytest -q

test-all: $(STAMP)
	$(BIN)/python -m pytest -q -m ''

## bench: speed and memory of every stage, written to bench-results.json
bench: $(STAMP)
	$(BIN)/python -m mst.eval.bench --out bench-results.json

lint: $(STAMP)
	$(BIN)/python -m ruff check .

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache bench-results.json
