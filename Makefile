# alignrl: the two commands are `make run` and `make test` (see README.md).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install run test lint format bench scenarios clean

$(STAMP): pyproject.toml
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	# The pinned CPU build of torch lies on these machines' disk; an unpinned torch downloads gigabytes.
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# The benchmark extra (Stable-Baselines3) on top of the dev install; `make test` never needs it.
BENCH_STAMP := $(VENV)/.installed-bench
$(BENCH_STAMP): $(STAMP)
	$(BIN)/pip install --quiet -e '.[dev,bench]'
	touch $(BENCH_STAMP)

# The most complete end-to-end job so far: record a small scenario set on the synthetic SEM,
# validate it strictly and plot its focus curves; run the classical autofocus baselines on a
# simulator replaying it; train a SAC aligner briefly and evaluate it on held-out scenarios
# beside the baselines. Everything lands in runs/make-run/ (replaced on every `make run`).
RUN_DIR := runs/make-run
run: $(STAMP)
	rm -rf $(RUN_DIR)
	$(BIN)/alignrl record --apparatus synthetic --scenarios 40 --seed 0 \
		--out $(RUN_DIR)/scenarios.csv
	$(BIN)/alignrl scenarios validate $(RUN_DIR)/scenarios.csv --plot $(RUN_DIR)/focus-curves.png
	$(BIN)/alignrl baselines --apparatus csv:$(RUN_DIR)/scenarios.csv --scenarios 40 \
		--plot-dir $(RUN_DIR)/baselines
	$(BIN)/alignrl train experiments/make-run.yaml --runs-dir $(RUN_DIR)
	$(BIN)/alignrl evaluate --policy $(RUN_DIR)/make-run --apparatus csv:default \
		--apparatus-args '{"noise": 0.02, "split": "test"}' --scenarios 100 \
		--plot $(RUN_DIR)/trained-aligner.png
	$(BIN)/alignrl baselines --apparatus csv:default \
		--apparatus-args '{"noise": 0.02, "split": "test"}' --scenarios 100

test: $(STAMP)
	$(BIN)/ruff check alignrl tests benchmarks docs/examples
	$(BIN)/ruff format --check alignrl tests benchmarks docs/examples
	$(BIN)/pytest

lint: $(STAMP)
	$(BIN)/ruff check alignrl tests benchmarks docs/examples

format: $(STAMP)
	$(BIN)/ruff format alignrl tests benchmarks docs/examples
	$(BIN)/ruff check --fix alignrl tests benchmarks docs/examples

bench: $(BENCH_STAMP)
	$(BIN)/python -m benchmarks.run --out docs/benchmarks.md

# Regenerate the shipped 2000-scenario set of the `synthetic` preset (deterministic).
scenarios: $(STAMP)
	$(BIN)/alignrl record --apparatus synthetic --scenarios 2000 --seed 0 --step adaptive \
		--workers 2 --force --out alignrl/data/scenarios-synthetic.csv.gz

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
