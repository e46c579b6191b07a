# The two set-up commands of the README: `make run` and `make test`.
# Both create the virtualenv (.venv) on first use, so a fresh clone needs nothing else
# than Python 3.11 with venv.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV ?= .venv
BIN = $(VENV)/bin
# Real data for tests and benchmarks (mazes, pose graphs, laser logs) lives outside the
# repository: ../shared/data where there is one (CI), else data/ in the checkout, which
# `make data` fills from the data's origins; tests that need it skip with a reason without it.
MAZEBOT_DATA ?= $(firstword $(wildcard $(CURDIR)/../shared/data /work/shared/data) $(CURDIR)/data)
export MAZEBOT_DATA

.PHONY: run test test-fast lint system-deps data check-install check-lock clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $@

run: $(BIN)/.installed
	$(BIN)/mazebot run --sim

# ruff (style), lint-imports (the import layers of pyproject.toml), mypy (types; strict on io/,
# slam/, planner/ and the hardware boundary)
lint: $(BIN)/.installed
	$(BIN)/ruff check .
	$(BIN)/lint-imports
	$(BIN)/mypy

system-deps:
	bash tools/system-deps.sh

test: system-deps lint
	$(BIN)/pytest

# the inner loop: the tests not marked slow (closed-loop runs, browser and subprocess tests)
test-fast: $(BIN)/.installed
	$(BIN)/pytest -m "not slow"

data:
	$(PYTHON) tools/fetch_data.py --data $(MAZEBOT_DATA)

# CI's checks beyond the test suite (.ci/run): the wheel installed outside the checkout (a fresh
# venv and pip install --user) serves the page; the Pi's lock file still resolves.
check-install:
	$(PYTHON) tools/check_install.py --python $(PYTHON)

UV_VERSION ?= 0.13.9
check-lock: $(BIN)/.installed
	$(BIN)/python -m pip install --quiet 'uv==$(UV_VERSION)'
	UV=$(BIN)/uv bash tools/lock-pi.sh --check

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
