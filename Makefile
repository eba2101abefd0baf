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
# `make test-slow`, and CI runs both.
test: $(STAMP)
	$(BIN)/python -m pytest -m "not slow"

test-slow: $(STAMP)
	$(BIN)/python -m pytest -m slow

bench-quick: $(STAMP)
	$(BIN)/python benchmarks/bench.py --quick --out "$$(mktemp -d)"

lint: $(STAMP)
	$(BIN)/pip install --quiet ruff && $(BIN)/ruff check . && $(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) .pytest_cache
