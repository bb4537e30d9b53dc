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

# The most complete end-to-end job so far: record a small scenario set on the synthetic SEM,
# validate it strictly, print its summary and plot its focus curves.
RUN_DIR := runs/make-run
run: $(STAMP)
	$(BIN)/alignrl record --apparatus synthetic --scenarios 40 --seed 0 --force \
		--out $(RUN_DIR)/scenarios.csv
	$(BIN)/alignrl scenarios validate $(RUN_DIR)/scenarios.csv --plot $(RUN_DIR)/focus-curves.png

test: $(STAMP)
	$(BIN)/ruff check alignrl tests benchmarks docs/examples
	$(BIN)/ruff format --check alignrl tests benchmarks docs/examples
	$(BIN)/pytest

lint: $(STAMP)
	$(BIN)/ruff check alignrl tests benchmarks docs/examples

format: $(STAMP)
	$(BIN)/ruff format alignrl tests benchmarks docs/examples
	$(BIN)/ruff check --fix alignrl tests benchmarks docs/examples

bench: $(STAMP)
	$(BIN)/python -m benchmarks.run --out docs/benchmarks.md

# Regenerate the shipped 2000-scenario set of the `synthetic` preset (deterministic).
scenarios: $(STAMP)
	$(BIN)/alignrl record --apparatus synthetic --scenarios 2000 --seed 0 --step adaptive \
		--workers 2 --force --out alignrl/data/scenarios-synthetic.csv.gz

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
