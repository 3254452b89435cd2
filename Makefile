# Two commands on a fresh machine: `make demo` and `make test`.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-slow bench install clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/needletissue reproduce --out results/

test: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

# the version the FE benchmark compares with (before the issue-18 solver changes)
BENCH_PREVIOUS ?= efc877e

bench: $(STAMP)
	$(BIN)/python -m pytest -q benchmarks/ --benchmark-only -p no:cacheprovider
	$(BIN)/python benchmarks/bench_fe_needle.py --previous $(BENCH_PREVIOUS) --repeat 2 --write-docs  # refreshes docs/bench.md

clean:
	rm -rf $(VENV) results/ .pytest_cache
