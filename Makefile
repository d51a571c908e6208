# omnispectral: `make demo` runs the main job on the built-in default, `make test` runs the tests but the
# minutes-long ones, `make test-long` those (CI runs both), `make test-fast` leaves out the slow tests. All create
# (or reuse) the virtual environment .venv and install what is needed from PyPI.

PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.omnispectral-installed
DEMO_OUT ?= demo-output

.PHONY: demo test test-long test-fast lint bench clean venv

venv: $(STAMP)

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 11), "omnispectral needs Python >= 3.11"'
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV) || { \
		echo "python3 -m venv failed: installing Debian's python3-venv"; \
		apt-get update -qq && apt-get install -y -qq python3-venv && $(PYTHON) -m venv $(VENV); }
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[all,test,bench]'
	@touch $(STAMP)

demo: $(STAMP)
	$(BIN)/omnispectral demo --out $(DEMO_OUT)
	$(BIN)/omnispectral spectral evaluate --plot $(DEMO_OUT)/spectral_evaluation.png \
		--json-out $(DEMO_OUT)/spectral_evaluation.json

test: $(STAMP)  # everything but the tests marked long (make test-long)
	$(BIN)/ruff check src tests benchmarks scripts
	$(BIN)/python -m pytest -q -m "not long"

test-long: $(STAMP)  # the tests that run for minutes: every README command line as written
	$(BIN)/python -m pytest -q -m long

test-fast: $(STAMP)  # the edit-test loop: everything but the tests marked slow
	$(BIN)/ruff check src tests benchmarks scripts
	$(BIN)/python -m pytest -q -m "not slow"

lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks scripts

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_spectral.py
	for b in benchmarks/bench_*.py; do [ "$$b" = benchmarks/bench_spectral.py ] || $(BIN)/python $$b; done

bench-deps:  # Hugin's nona, the baseline of benchmarks/bench_mosaic.py (Debian hugin-tools)
	command -v nona >/dev/null || { apt-get update -qq && apt-get install -y -qq --no-install-recommends hugin-tools; }

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache build src/*.egg-info
