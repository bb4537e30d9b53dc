# alignrl: the two commands are `make run` and `make test` (see README.md).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install run test test-all test-fast learning-check docs-check crash-check report-check \
	lint format bench scenarios clean

$(STAMP): pyproject.toml
	test -d $(VENV) || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	# The pinned CPU build of torch lies on these machines' disk; an unpinned torch downloads gigabytes.
	$(BIN)/pip install --quiet torch==2.13.0
	# The onnx and ray extras too: their tests (export parity, the Ray backend) run in `make test`.
	$(BIN)/pip install --quiet -e '.[dev,onnx,ray]'
	touch $(STAMP)

install: $(STAMP)

# The benchmark extra (Stable-Baselines3) on top of the dev install; `make test` never needs it.
BENCH_STAMP := $(VENV)/.installed-bench
$(BENCH_STAMP): $(STAMP)
	$(BIN)/pip install --quiet -e '.[dev,onnx,ray,bench]'
	touch $(BENCH_STAMP)

# The main job: the shipped champions beside the classical controllers on columns they never
# trained on (`alignrl champions`: focus-v2 on the held-out instruments, the stigmation,
# aperture and column champions on the second preset), then a short league of the default
# rosters (populations/) that ends with its leaderboard, its champion aligner beside the same
# member untrained and the classical controllers on the same held-out scenarios, and its
# report (runs/make-run/league-make-run/report.md). Replaced on every `make run`.
RUN_DIR := runs/make-run
run: $(STAMP)
	rm -rf $(RUN_DIR)
	$(BIN)/alignrl champions --scenarios 5
	$(BIN)/alignrl league run experiments/league-make-run.yaml --runs-dir $(RUN_DIR)

# The suite, slow tests included, on two workers; a test file stays on one worker
# (--dist loadfile), so a file's module fixtures are built once. The tests marked long
# (minutes of one worker each: `make run` with the commands that read its league, the
# README's held-out table of the champion, the crash windows' kills at every other write) run in `make docs-check`, `make crash-check` and
# `make test-all` instead; the three marked learning (whole training runs on focus and on the
# stigmators and an adaptation, each of which must end well above an untrained learner, 20 to
# 40 s each; `make test` keeps a shorter check of each kind) in `make learning-check`.
PYTEST := $(BIN)/pytest -n 2 --dist loadfile
test: $(STAMP)
	$(BIN)/ruff check alignrl tests benchmarks docs/examples docs/gen_configs.py
	$(BIN)/ruff format --check alignrl tests benchmarks docs/examples docs/gen_configs.py
	$(PYTEST) -m "not long and not learning"

# The learning checks `make test` leaves out (tests marked learning).
learning-check: $(STAMP)
	$(PYTEST) -m learning

# Every test, the long ones included.
test-all: $(STAMP)
	$(PYTEST)

# Everything but the tests marked slow or long (over about 15 s each: the crash windows, the
# docs commands that train a league), for the edit-test loop.
test-fast: $(STAMP)
	$(PYTEST) -m "not slow and not long and not learning"

# Every command and example the README and docs/ show, run and compared with what they show.
docs-check: $(STAMP)
	$(PYTEST) tests/test_docs_readme.py tests/test_docs_manual.py tests/test_docs_shown.py \
		tests/test_configs_doc.py

# A league and a trainer killed at every write boundary of a tiny run, resumed, and compared
# with an uninterrupted run (`make test` kills at the writes of the snapshot window and every
# tenth before it; this adds the writes it leaves out).
crash-check: $(STAMP)
	$(PYTEST) tests/test_crash_windows.py

# The HTML reports in a real browser: headless Chromium renders a small league's report.html
# and a training run's; every figure must load and show. Needs Chromium (Debian: `apt-get
# install chromium`; CI has none, so there the test is skipped). The pages and their
# screenshots stay in runs/report-check/.
REPORT_CHECK_DIR := runs/report-check
report-check: $(STAMP)
	@command -v chromium >/dev/null || command -v chromium-browser >/dev/null \
		|| command -v google-chrome >/dev/null \
		|| { echo "make report-check: no Chromium on PATH; install it (Debian: apt-get install chromium)" >&2; exit 1; }
	rm -rf $(REPORT_CHECK_DIR)
	$(BIN)/pytest tests/test_report_browser.py --basetemp=$(REPORT_CHECK_DIR) -p no:cacheprovider
	@find $(REPORT_CHECK_DIR) -name 'report.png' | sort

lint: $(STAMP)
	$(BIN)/ruff check alignrl tests benchmarks docs/examples docs/gen_configs.py

format: $(STAMP)
	$(BIN)/ruff format alignrl tests benchmarks docs/examples docs/gen_configs.py
	$(BIN)/ruff check --fix alignrl tests benchmarks docs/examples docs/gen_configs.py

bench: $(BENCH_STAMP)
	$(BIN)/python -m benchmarks.run --out docs/benchmarks.md

# Regenerate the shipped 2000-scenario set of the `synthetic` preset (deterministic).
scenarios: $(STAMP)
	$(BIN)/alignrl record --apparatus synthetic --scenarios 2000 --seed 0 --step adaptive \
		--workers 2 --force --out alignrl/data/scenarios-synthetic.csv.gz

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
