# Two set-up commands (see README): `make run` and `make test`.
# Each creates .venv on first use and reinstalls only when pyproject.toml changes.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test test-slow lint bench-quick clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[test]"
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/fosmc reproduce --out out/reproduction --force

# The default tier; the tests marked slow (long horizons, many compilations) run in
# `make test-slow`, and CI runs both. One pytest-xdist worker per core, whole files per
# worker (module fixtures compile once): 5m50 -> 3m44 on 2 cores, most of a test's time
# being single-threaded XLA compilation.
JOBS ?= $(shell nproc)
test: $(STAMP)
	$(BIN)/python -m pytest -m "not slow" -n $(JOBS) --dist loadfile

test-slow: $(STAMP)
	$(BIN)/python -m pytest -m slow -n $(JOBS) --dist loadfile

bench-quick: $(STAMP)
	$(BIN)/python benchmarks/bench.py --quick --out "$$(mktemp -d)"

lint: $(STAMP)
	$(BIN)/pip install --quiet ruff && $(BIN)/ruff check . && $(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) .pytest_cache
