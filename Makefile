# Quick start: `make run` trains with the local cluster, `make test` runs the test suite.
# Both build .venv first.
# Override the torch build with e.g. `make test TORCH_SPEC='torch==2.5.1'`.
PYTHON ?= python3
VENV ?= .venv
TORCH_SPEC ?= torch==2.13.0
BIN := $(VENV)/bin
ARGS ?=

.PHONY: install run serial test lint bench-replay bench-learn bench-throughput bench-bandwidth \
	bench-snapshot bench-fuzz bench-soak bench-paper clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet "$(TORCH_SPEC)"
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $@

install: $(VENV)/.installed

run: install
	$(BIN)/tpdeb-cluster --cluster-file deploy/local.toml $(ARGS)

serial: install
	$(BIN)/tpdeb-train --env-id HalfCheetah-v5 $(ARGS)

test: install
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q --durations=25

lint: install
	$(BIN)/ruff check .

bench-replay: install
	$(BIN)/python bench/replay_ops.py

bench-learn: install
	$(BIN)/python bench/learn.py

bench-throughput: install
	$(BIN)/python bench/throughput.py

bench-bandwidth: install
	$(BIN)/python bench/bandwidth.py

bench-snapshot: install
	$(BIN)/python bench/replay_snapshot.py $(ARGS)

# Every protocol fuzz test at 10,000 cases, per message type where a test runs per type
# (ARGS="--examples 100000" for more).
bench-fuzz: install
	$(BIN)/python bench/fuzz.py $(ARGS)

# 10 minutes of the local cluster, RSS drift per service (ARGS='--minutes 30' for longer).
bench-soak: install
	$(BIN)/python bench/soak.py $(ARGS)

# The paper's comparison: 6 tasks × TPDEB/IMPACT/PPO+PER × seeds 11-13 × 1M steps, resumable
# (hours); ARGS='--report' rewrites docs/RESULTS.md from the finished runs.
bench-paper: install
	$(BIN)/python bench/paper.py $(ARGS)

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
