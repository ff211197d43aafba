# Two commands for a fresh machine (Python 3.11, pip, make, gcc): `make demo`, `make test`.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
BENCH_STAMP := $(VENV)/.installed-bench

.PHONY: demo test test-all bench lint check clean

$(STAMP): pyproject.toml
	@command -v $(PY) >/dev/null 2>&1 || { echo "error: $(PY) not found (need Python >= 3.11)"; exit 2; }
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/tagtrail demo

# The fast tier (a few minutes): every test but those marked slow.
test: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

# Every test, the slow ones included (accuracy, real data, clusters, crashes): what CI runs.
test-all: $(STAMP)
	$(BIN)/python -m pytest -q

# The benchmarks' extra (gtsam) on top of the test install; `make test` does not need it.
$(BENCH_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	touch $(BENCH_STAMP)

# Every benchmark in one run (~8 min on 2 cores): writes bench/RESULTS.md.
bench: $(BENCH_STAMP)
	$(BIN)/python bench/run_all.py

lint: $(STAMP)
	$(BIN)/ruff check tagtrail tests bench
	$(BIN)/ruff format --check tagtrail tests bench
	$(BIN)/mypy tagtrail

check: lint test-all

clean:
	rm -rf $(VENV) artifacts outputs demo
