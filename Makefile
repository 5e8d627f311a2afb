# radarseg: the two commands are `make demo` and `make test`; both build .venv first.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

export RAY_AUTH_MODE ?= disabled
export RAY_USAGE_STATS_ENABLED ?= 0

.PHONY: venv test test-fast demo lint bench clean

venv: $(STAMP)

# Re-installs only when pyproject.toml changes; torch is pinned to the CPU wheel on local disk.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

test: venv
	$(BIN)/python -m pytest -q

# The day-to-day lane: everything but the slow and Ray tests (CI runs the full `make test`).
test-fast: venv
	$(BIN)/python -m pytest -q -m "not slow and not ray"

demo: venv
	$(BIN)/radarseg demo --out out/demo

lint: venv
	$(BIN)/ruff check .

# Every benchmark, one after the other (about 10 minutes on 2 idle cores); figures in benchmarks/results/.
BENCHMARKS := simulate detector stage1 sparse_conv end_to_end preprocess service scale baselines compare export

bench: venv
	for b in $(BENCHMARKS); do echo "== benchmarks/$$b.py"; $(BIN)/python -m benchmarks.$$b || exit 1; done

clean:
	rm -rf out .pytest_cache
