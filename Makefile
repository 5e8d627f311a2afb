# radarseg: the two commands are `make demo` and `make test`; both build .venv first.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

export RAY_AUTH_MODE ?= disabled
export RAY_USAGE_STATS_ENABLED ?= 0

.PHONY: venv clean-venv test test-fast test-deploy demo lint bench clean

# torch is pinned in pyproject.toml; which build of it is installed is chosen here:
#   TORCH_VARIANT=cpu  (default) the CPU build, about 200 MB, from PyTorch's CPU index (its "+cpu" wheel outranks
#                      PyPI's build of the same version; torch alone comes from there, its dependencies from PyPI
#                      with the project's); where a local wheel folder already holds it (our CI), pip takes that
#                      one and only warns that the index cannot be reached
#   TORCH_VARIANT=cuda PyPI's default build, with CUDA (several GB)
#   TORCH_INDEX=URL    another index for torch (a mirror, or https://download.pytorch.org/whl/cu126 for one CUDA)
TORCH_VERSION := $(shell sed -n 's/.*"torch==\([^"]*\)".*/\1/p' pyproject.toml)
TORCH_VARIANT ?= cpu
TORCH_INDEX ?= $(if $(filter cpu,$(TORCH_VARIANT)),https://download.pytorch.org/whl/cpu,)

venv: $(STAMP)

# Re-installs only when pyproject.toml changes (or the torch choice is changed by hand: `make clean-venv`).
$(STAMP): pyproject.toml
	@echo "set-up: .venv with torch $(TORCH_VERSION) ($(TORCH_VARIANT) build$(if $(TORCH_INDEX), from $(TORCH_INDEX),)) and the project's dependencies; this takes a few minutes"
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet --no-deps 'torch==$(TORCH_VERSION)' $(if $(TORCH_INDEX),--extra-index-url $(TORCH_INDEX),)
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	@$(BIN)/python -c "import torch; print(f'set-up done: torch {torch.__version__}, CUDA available: {torch.cuda.is_available()}')"
	@# the compiled sparse engine, built now for this CPU rather than by the first test, job or service start
	@$(BIN)/python -c "from models.sparse import compiled; compiled.load(); print('set-up: compiled sparse engine ready')" \
		|| echo "set-up: the compiled sparse engine did not build; the pure-PyTorch engine will run (README)"
	touch $(STAMP)

# The suite runs on one pytest-xdist worker per core (TEST_WORKERS=0 runs it in this process); the Ray tests
# share one worker (tests/conftest.py), so one cluster runs at a time.
TEST_WORKERS ?= auto
PYTEST := $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadgroup --durations=30

test: venv
	$(PYTEST)

# The day-to-day lane: everything but the slow and Ray tests (CI runs the full `make test`).
test-fast: venv
	$(PYTEST) -m "not slow and not ray"

# The compose stack on a real Docker engine (tests/deploy/test_compose_stack.py): offline base images, the image,
# two Ray workers and two API replicas with PostgreSQL, driven and torn down (deploy/README.md). Skipped without
# an engine; RADARSEG_REQUIRE_DOCKER=1 makes a missing engine a failure (CI).
test-deploy: venv
	RADARSEG_DEPLOY_LANE=1 $(BIN)/python -m pytest -q -x -n 0 --durations=0 tests/deploy/test_compose_stack.py

demo: venv
	$(BIN)/radarseg demo --out out/demo

lint: venv
	$(BIN)/ruff check .

# Every registered benchmark that runs on the repository alone, one after the other (benchmarks/harness.py): the
# latest figures in benchmarks/results/NAME.json, each run appended to benchmarks/results/history/NAME.jsonl.
bench: venv
	$(BIN)/python -m benchmarks run --all

clean:
	rm -rf out .pytest_cache

# To switch the torch build: make clean-venv && make venv TORCH_VARIANT=cuda
clean-venv:
	rm -rf $(VENV)
